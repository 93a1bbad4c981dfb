"""`trapflow process` on a real Dask LocalCluster (2 worker processes) and on an existing
scheduler: the live pipeline's results pair for pair, resume, failed chunks, no leftovers."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import psutil
import pytest

from tests.builders import floor_scene
from tests.conftest import (
    REPO,
    Pipeline,
    only_pools,
    poll_for,
    read_lines,
    run_process,
    write_config,
)
from trapflow.calibration.camera import StereoRig

pytestmark = pytest.mark.slow  # starts whole pipelines

PLUGIN = "tests.integration.batch_plugins:FailChunk"
N = 10


def write_scene(root: Path, n: int = N) -> Path:
    """An image folder of a textured floor with an AprilTag, the rig moving over it."""
    rig = StereoRig.from_fov(320, 240, 70.0, 0.12)
    pairs, _poses = floor_scene(rig, n)
    for name in ("left", "right"):
        (root / name).mkdir(parents=True)
    for i, (left, right) in enumerate(pairs):
        cv2.imwrite(str(root / "left" / f"{i:06d}.png"), left)
        cv2.imwrite(str(root / "right" / f"{i:06d}.png"), right)
    return root


def by_pair(lines: list[dict[str, Any]]) -> dict[int, list[str]]:
    """Result lines per pair, without what differs between runs by design: the time label,
    and the track ids, which follow from capture times (the live run's wall clock, the
    re-analysis' position x rate for a folder without times)."""
    out: dict[int, list[str]] = defaultdict(list)
    for line in lines:
        (name, body), = line.items()
        body = {k: v for k, v in body.items() if k not in ("timestamp", "track")}
        out[body["seq"]].append(json.dumps({name: body}, sort_keys=True))
    return {seq: sorted(v) for seq, v in out.items()}


@pytest.mark.timeout(180)
def test_process_equals_the_live_pipeline_pair_for_pair(spawn, run_dir: Path) -> None:
    """The same folder through `trapflow start --source images:` and through `process`
    (stateless pools in chunks of 3, VO whole) gives the same results for every pair."""
    scene = write_scene(run_dir.parent / "scene")
    # Every pair through every pool in the live run too (batch has no motion gate).
    pools = {"mono": {"count": 1, "policy": "fifo:64", "gate": "always"},
             "stereo": {"count": 1, "policy": "fifo:64", "gate": "always"},
             "vo": {"count": 1, "policy": "ordered:64"},
             "tags": {"count": 1, "policy": "fifo:64"}}
    cfg = write_config(run_dir.parent / "c.yaml", {"pools": only_pools(pools)})
    live: Pipeline = spawn(["--config", str(cfg), "--source", f"images:{scene}",
                            "--rate", "10"], run_dir)
    code, _out, err = live.wait(120)
    assert code == 0, err
    out = run_dir.parent / "out"
    code, stdout, err = run_process([str(scene), "--config", str(cfg), "--out", str(out),
                                     "--local", "2", "--chunk", "3"])
    assert code == 0, err
    batch = read_lines(out / "scene" / "results.jsonl")
    want = by_pair(live.results())
    assert sorted(want) == list(range(N))
    assert by_pair(batch) == want
    seqs = [next(iter(x.values()))["seq"] for x in batch]
    assert seqs == sorted(seqs), "results.jsonl is not in time order"
    # Re-analysis tracks too, over the whole input across its chunks.
    boxes = [x["mono_ir"] for x in batch if x.get("mono_ir", {}).get("label", "none") != "none"]
    assert boxes and all("track" in b for b in boxes)
    tracks = read_lines(out / "scene" / "tracks.jsonl")
    assert {b["track"] for b in boxes} - {None} <= {t["track"]["id"] for t in tracks}
    # VO's chained poses reach the re-analysis' tracks as the live normalizer's: speeds
    # over the ground.
    frames = {t["track"].get("speed_frame") for t in tracks} - {None}
    assert frames <= {"ground"}
    assert "; dashboard " in err and "pairs/s" in err and "ETA" in err
    ledger = json.loads((out / "scene" / "ledger.json").read_text())
    assert ledger["read"] == N and ledger["processed"] == dict.fromkeys(pools, N)
    assert "scene: 10/10 pairs read" in stdout


@pytest.mark.timeout(120)
def test_vo_chunks_report_their_boundaries_and_chain_the_poses(tmp_path: Path) -> None:
    """VO in chunks of 4 with an overlap of 2: each boundary is reported with the drift it
    costs, and the chained poses follow the whole-sequence run's within that drift."""
    scene = write_scene(tmp_path / "scene")
    whole, chunked = tmp_path / "whole", tmp_path / "chunked"
    code, _o, err = run_process([str(scene), "--workers", "vo", "--out", str(whole),
                                 "--local", "2"])
    assert code == 0, err
    code, _o, err = run_process([str(scene), "--workers", "vo", "--out", str(chunked),
                                 "--local", "2", "--vo-chunk", "4", "--vo-overlap", "2"])
    assert code == 0, err
    ledger = json.loads((chunked / "scene" / "ledger.json").read_text())
    assert [b["at"] for b in ledger["vo_boundaries"]] == [4, 8]
    assert all(b["overlap"] == 2 and b["compared_seq"] == b["at"] - 1
               and b["drift_translation_m"] is not None for b in ledger["vo_boundaries"])
    a = {x["stereo_vo"]["seq"]: x["stereo_vo"] for x in read_lines(whole / "scene" /
                                                                    "results.jsonl")}
    b = {x["stereo_vo"]["seq"]: x["stereo_vo"] for x in read_lines(chunked / "scene" /
                                                                    "results.jsonl")}
    assert sorted(a) == sorted(b) == list(range(N))
    assert [s for s in b if b[s].get("reinit")] == [0, 2, 6] or \
        [s for s in b if b[s].get("reinit")] == [0], "overlap pairs leaked into the results"
    worst = sum(x["drift_translation_m"] for x in ledger["vo_boundaries"]) + 0.01
    for s in range(N):
        ta = [row[3] for row in a[s]["pose"]]
        tb = [row[3] for row in b[s]["pose"]]
        assert max(abs(p - q) for p, q in zip(ta, tb, strict=True)) <= worst, s


@pytest.mark.timeout(150)
def test_a_failed_chunk_is_retried_reported_and_a_rerun_resumes(tmp_path: Path) -> None:
    """A chunk that fails is retried by Dask, then reported with its error while the others
    finish; the same command again skips the finished chunks and does only that one."""
    scene = write_scene(tmp_path / "scene")
    tally = tmp_path / "tally.txt"
    cfg = write_config(tmp_path / "c.yaml", {"pools": only_pools({"f": {
        "plugin": PLUGIN, "params": {"first": 4, "tally": str(tally),
                                     "marker": str(tmp_path / "failed-once")}}})})
    out = tmp_path / "out"
    args = [str(scene), "--config", str(cfg), "--workers", "f", "--out", str(out),
            "--local", "2", "--chunk", "2"]
    # With one retry, the chunk that fails once succeeds on its second run.
    code, _o, err = run_process([*args, "--retries", "1"])
    assert code == 0, err
    assert tally.read_text().split() == ["4", "4"]
    # Without retries it fails for good: reported, the other chunks finished.
    (tmp_path / "failed-once").unlink()
    tally.unlink()
    out2 = tmp_path / "out2"
    args[args.index(str(out))] = str(out2)
    code, stdout, err = run_process([*args, "--retries", "0"])
    assert code == 1
    assert "chunk f-00000004-00000006" in err and "fails on purpose" in err
    ledger = json.loads((out2 / "scene" / "ledger.json").read_text())
    status = {c["chunk"]: c["status"] for c in ledger["chunks"]}
    assert status == {f"f-{a:08d}-{a + 2:08d}": ("failed" if a == 4 else "done")
                      for a in range(0, N, 2)}
    assert ledger["processed"] == {"f": N - 2}
    done = {p.name: p.stat().st_mtime_ns for p in (out2 / "scene" / "chunks").iterdir()}
    assert len(done) == 2 * 4  # lines + ledger of the 4 finished chunks, none of the failed
    # The same command again: only the failed chunk runs.
    code, _o, err = run_process([*args, "--retries", "0"])
    assert code == 0, err
    assert "resume: 4 finished chunks" in err
    assert tally.read_text().split() == ["4", "4"]
    for name, mtime in done.items():
        assert (out2 / "scene" / "chunks" / name).stat().st_mtime_ns == mtime, name
    ledger = json.loads((out2 / "scene" / "ledger.json").read_text())
    assert ledger["processed"] == {"f": N}
    assert [next(iter(x.values()))["seq"] for x in read_lines(out2 / "scene" /
                                                               "results.jsonl")] == list(range(N))


@pytest.mark.timeout(120)
def test_an_existing_scheduler_by_address(tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """`--scheduler ADDRESS` runs the chunks on a cluster started elsewhere (here, by the
    test) and leaves that cluster running."""
    from dask.distributed import Client, LocalCluster

    # Dask's nanny writes its pre-spawn environment (MALLOC_TRIM_THRESHOLD_) into this
    # process's os.environ; recorded here so that it is undone after the test.
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "")
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_")

    scene = write_scene(tmp_path / "scene", 6)
    out = tmp_path / "out"
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        workers = set(cluster.scheduler_info["workers"])
        code, stdout, err = run_process_remote([str(scene), "--workers", "mono,tags", "--out",
                                                str(out), "--scheduler",
                                                cluster.scheduler_address, "--chunk", "2"])
        assert code == 0, err
        with Client(cluster) as client:
            assert set(client.scheduler_info()["workers"]) == workers
        ledger = json.loads((out / "scene" / "ledger.json").read_text())
        assert ledger["processed"] == {"mono": 6, "tags": 6}
        assert {c["status"] for c in ledger["chunks"]} == {"done"}
    _gone, alive = psutil.wait_procs(
        [p for p in psutil.Process().children(recursive=True)
         if p.pid not in before and not is_resource_tracker(p)], timeout=10)
    assert not alive, f"cluster processes left: {[p.cmdline() for p in alive]}"


def is_resource_tracker(p: psutil.Process) -> bool:
    """multiprocessing's resource tracker: one per parent process, it lives as long as the
    test session (the cluster's processes, not it, must be gone)."""
    try:
        return "resource_tracker" in " ".join(p.cmdline())
    except psutil.NoSuchProcess:
        return True


def run_process_remote(args: list[str], timeout: float = 90) -> tuple[int, str, str]:
    """`trapflow process` as a client only: it starts no worker process of its own."""
    out = subprocess.run([sys.executable, "-m", "trapflow", "process", *args],
                         capture_output=True, text=True, timeout=timeout, cwd=REPO)
    return out.returncode, out.stdout, out.stderr


def _named_semaphores(pids: list[int]) -> set[Path]:
    """The POSIX named semaphores (/dev/shm/sem.*) these processes have mapped: what a kill -9
    of them leaves behind, and only theirs."""
    out: set[Path] = set()
    for pid in pids:
        try:
            maps = Path(f"/proc/{pid}/maps").read_text()
        except OSError:
            continue
        out |= {Path(line.split()[-1]) for line in maps.splitlines()
                if line.rstrip().split()[-1].startswith("/dev/shm/sem.")}
    return out


def _all_gone(sems: set[Path], within_s: float = 15.0) -> None:
    """Every one of these semaphores leaves /dev/shm within within_s (removed if not, so a
    failure here leaves nothing behind)."""
    try:
        poll_for(lambda: not any(s.exists() for s in sems), within_s,
                 what=f"the killed run's semaphores to go: {sorted(map(str, sems))}")
    finally:
        for sem in sems:
            sem.unlink(missing_ok=True)


@pytest.mark.timeout(120)
def test_killed_as_its_cluster_starts_leaves_no_semaphore(tmp_path: Path) -> None:
    """Regression (issue 36 item 7): `trapflow process` killed (the whole process group, kill
    -9) in its first seconds, before Dask's cleaner was up, left 12 `sem.mp-*` in /dev/shm
    for good. Killed the moment its first named semaphore exists, none is left."""
    scene = write_scene(tmp_path / "scene")
    proc = subprocess.Popen(
        [sys.executable, "-m", "trapflow", "process", str(scene), "--workers", "vo",
         "--out", str(tmp_path / "out"), "--local", "2"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True, cwd=REPO)
    sems: set[Path] = set()
    try:
        deadline = time.monotonic() + 60
        while not sems:
            assert proc.poll() is None, "process ended before a semaphore was seen"
            assert time.monotonic() < deadline, "no named semaphore within 60 s"
            try:
                tree = [proc.pid, *(k.pid for k in psutil.Process(proc.pid).children(True))]
            except psutil.NoSuchProcess:
                continue
            sems = _named_semaphores(tree)
            time.sleep(0.01)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    _all_gone(sems)


@pytest.mark.timeout(150)
def test_killed_mid_run_then_resumed_skips_the_finished_chunks(tmp_path: Path) -> None:
    """kill -9 of the whole `process` (client, nannies, workers) mid-run, then the same
    command: the chunks finished before the kill are not run again, the rest are, and the
    results are complete. A chunk cut by the kill left no file that counts as finished."""
    scene = write_scene(tmp_path / "scene")
    cfg = write_config(tmp_path / "c.yaml", {"pools": only_pools({
        "s": {"plugin": "slow", "params": {"delay_s": 0.4}}})})
    out = tmp_path / "out"
    args = [sys.executable, "-m", "trapflow", "process", str(scene), "--config", str(cfg),
            "--workers", "s", "--out", str(out), "--local", "2", "--chunk", "1"]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True, cwd=REPO)
    chunks = out / "scene" / "chunks"
    seen: dict[int, psutil.Process] = {}

    def finished() -> list[Path]:
        for kid in psutil.Process(proc.pid).children(recursive=True):
            seen.setdefault(kid.pid, kid)
        return sorted(chunks.glob("*.json")) if chunks.is_dir() else []

    try:
        deadline = time.monotonic() + 60
        while len(finished()) < 2:
            assert proc.poll() is None, "process ended before it could be interrupted"
            assert time.monotonic() < deadline, "no chunk finished within 60 s"
            time.sleep(0.05)
    finally:
        sems = _named_semaphores([proc.pid, *seen])
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    _gone, alive = psutil.wait_procs(list(seen.values()), timeout=10)
    assert not [p.pid for p in alive if p.status() != psutil.STATUS_ZOMBIE]
    # Dask's multiprocessing semaphores: the cleaner outlived the kill and removed them
    # (trapflow/batch/cleaner.py; issue 36 item 7).
    _all_gone(sems)
    before = {p.name: p.stat().st_mtime_ns for p in chunks.iterdir()
              if not p.name.startswith(".")}
    done = [p for p in before if p.endswith(".json")]
    assert 2 <= len(done) < N, done
    code, _o, err = run_process(args[4:])
    assert code == 0, err
    assert f"resume: {len(done)} finished chunks" in err
    for name in done:
        assert (chunks / name).stat().st_mtime_ns == before[name], name
    ledger = json.loads((out / "scene" / "ledger.json").read_text())
    assert ledger["processed"] == {"s": N}
    assert sum(c["status"] == "resumed" for c in ledger["chunks"]) == len(done)
    assert [next(iter(x.values()))["seq"] for x in read_lines(out / "scene" /
                                                               "results.jsonl")] == list(range(N))


@pytest.mark.timeout(150)
def test_a_folder_tree_of_a_bag_and_a_recording_each_chunk_reads_its_own_pairs(
        tmp_path: Path) -> None:
    """A tree holding a ROS 2 bag (written by rosbags, one right frame missing) and a trapflow
    recording, cut into chunks of 2 on 2 workers: every pair's Digest of its decoded pixels
    equals the digest of the images written into the file, computed here with OpenCV."""
    import hashlib

    from rosbags.rosbag2 import StoragePlugin

    from tests.builders import img, write_bag, write_trapflow

    tree = tmp_path / "deploy"
    (tree / "day1").mkdir(parents=True)
    write_bag(tree / "day1" / "bag", 8, StoragePlugin.SQLITE3, drop_right=3)
    write_trapflow(tree / "run.mcap", 5)
    cfg = write_config(tmp_path / "c.yaml", {"source": {"encoding": "raw"},
                                             "pools": only_pools({"d": {"plugin": "digest"}})})
    out = tmp_path / "out"
    code, stdout, err = run_process([str(tree), "--config", str(cfg), "--workers", "d",
                                     "--out", str(out), "--local", "2", "--chunk", "2"])
    assert code == 0, err

    def digest(left: Any, right: Any) -> str:
        h = hashlib.sha1(left.tobytes())
        h.update(right.tobytes())
        return h.hexdigest()[:16]

    def jpeg(i: int, side: int) -> Any:
        return cv2.imdecode(cv2.imencode(".jpg", img(i, side))[1], cv2.IMREAD_COLOR)

    want = {
        "deploy__day1__bag": [digest(img(i, 0), img(i, 1)) for i in (0, 1, 2, 4, 5, 6, 7)],
        "deploy__run.mcap": [digest(jpeg(i, 0), jpeg(i, 1)) for i in range(5)],
    }
    for name, digests in want.items():
        got = [x["digest"] for x in read_lines(out / name / "results.jsonl")]
        assert [x["seq"] for x in got] == list(range(len(digests))), name
        assert [x["sha1"] for x in got] == digests, name
        assert f"{name}: {len(digests)}/{len(digests)} pairs read" in stdout
