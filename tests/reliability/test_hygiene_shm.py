"""Nothing of a run outlives it in /dev/shm: power cuts (kill -9 of the whole process group)
of the test's own pipelines, then one clean start.

Pins issue 16, item 10: every kill -9 of the process group left three `sem.mp-*` named
semaphores (multiprocessing's log queue) in /dev/shm that nothing removed. Only what the
test's own runs created is counted: the /dev/shm files their processes had open or mapped
(named semaphores carry no pid in their names), and ring segments named with their pids.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import psutil
import pytest

from tests.builders import small_source
from tests.conftest import Pipeline, only_pools, write_config
from tests.reliability import figures, scaled
from trapflow.wire.frame_ring import PREFIX, SHM_DIR, list_segments

pytestmark = pytest.mark.slow  # starts whole pipelines

CUTS = int(scaled("TRAPFLOW_CHAOS_CUTS", 3))
SMALL = small_source(10, kind="synthetic")


def _shm_files(pids: list[int]) -> set[str]:
    """Names under /dev/shm that these processes have open or mapped (read from /proc)."""
    names: set[str] = set()
    for pid in pids:
        try:
            with open(f"/proc/{pid}/maps") as f:
                for line in f:
                    path = line.rstrip("\n").split(None, 5)[-1]
                    if path.startswith(SHM_DIR + "/"):
                        names.add(path[len(SHM_DIR) + 1:].removesuffix(" (deleted)"))
            for fd in os.listdir(f"/proc/{pid}/fd"):
                try:
                    target = os.readlink(f"/proc/{pid}/fd/{fd}")
                except OSError:
                    continue
                if target.startswith(SHM_DIR + "/"):
                    names.add(target[len(SHM_DIR) + 1:].removesuffix(" (deleted)"))
        except (FileNotFoundError, ProcessLookupError, PermissionError):
            continue
    return names


def _group(p: Pipeline) -> list[int]:
    return [p.proc.pid, *(k.pid for k in p.track())]


@pytest.mark.timeout(60 + 40 * CUTS)
def test_power_cuts_of_the_process_group_leave_nothing_in_dev_shm(spawn, run_dir: Path
                                                                   ) -> None:
    cfg = write_config(run_dir.parent / "s.yaml", {
        "source": SMALL, "pools": only_pools({"vo": {"count": 1}, "mono": {"count": 1}})})
    seen: set[str] = set()  # what the test's runs had in /dev/shm
    pids: set[str] = set()  # its supervisors' pids, as ring segment names carry them
    for i in range(CUTS):
        p: Pipeline = spawn(["--config", str(cfg)], run_dir / f"cut{i}")
        p.wait_active()
        group = _group(p)
        assert len(group) >= 5, group
        held = _shm_files(group)
        assert any(n.startswith(f"{PREFIX}{p.proc.pid}-") for n in held), held
        seen |= held
        pids.add(str(p.proc.pid))
        os.killpg(p.proc.pid, signal.SIGKILL)  # the power cut: every process at once
        p.proc.wait(10)
        psutil.wait_procs([psutil.Process(q) for q in group if psutil.pid_exists(q)], 5)
    semaphores = sorted(n for n in seen if n.startswith("sem."))
    assert semaphores == [], f"a run created named semaphores: {semaphores}"
    final: Pipeline = spawn(["--config", str(cfg), "--duration", "2"], run_dir / "final")
    code, _, err = final.wait(60)
    assert code == 0, err
    left = sorted(n for n in seen if os.path.exists(os.path.join(SHM_DIR, n)))
    left += [n for n in list_segments()
             if n[len(PREFIX):].split("-", 1)[0] in pids | {str(final.proc.pid)}
             and n not in left]
    figures("shm_power_cuts", cuts=CUTS, shm_files_seen=len(seen), leaks=len(left))
    assert left == [], f"left in {SHM_DIR} by the test's runs: {left}"
