"""Who may enter a running pipeline: modes of the run directory, sockets, links, results and
the log under umask 000, another uid's connections, and control in TCP mode.

Pins issue 16, item 6: socket and directory modes followed the umask, so under umask 000
an unprivileged local user stopped the pipeline; in TCP mode any local user could, and
`trapflow status --run-dir` could not reach a TCP-mode pipeline at all.
"""

from __future__ import annotations

import errno
import json
import os
import pwd
import socket
import stat
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from tests.builders import small_source
from tests.conftest import REPO, Pipeline, free_base_port, only_pools, poll_for, write_config

pytestmark = pytest.mark.slow  # starts whole pipelines

SMALL = small_source(10, kind="synthetic")
POOLS = only_pools({"vo": {"count": 1}})


@contextmanager
def _umask(mask: int) -> Iterator[None]:
    """Children started inside inherit this umask (as a service or container would set)."""
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _connect_as_nobody(targets: list[tuple[str, int]]) -> dict[str, int]:
    """Path -> errno of a connect() from a child that dropped root for `nobody` (0: it got
    in). Skips the test when privileges cannot be dropped here."""
    if os.getuid() != 0:
        pytest.skip("needs root to drop privileges to another uid (os.setuid) in a child")
    try:
        nobody = pwd.getpwnam("nobody")
    except KeyError:
        pytest.skip("no user 'nobody' on this host to connect as")
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: no pytest, no zmq, only socket calls
        code = 1
        try:
            os.close(r)
            os.setgroups([])
            os.setgid(nobody.pw_gid)
            os.setuid(nobody.pw_uid)
            out: dict[str, int] = {"uid": os.getuid()}
            for path, kind in targets:
                s = socket.socket(socket.AF_UNIX, kind)
                try:
                    s.connect(path)
                    out[path] = 0
                except OSError as exc:
                    out[path] = exc.errno or -1
                finally:
                    s.close()
            os.write(w, json.dumps(out).encode())
            code = 0
        finally:
            os._exit(code)
    os.close(w)
    with os.fdopen(r, "rb") as f:
        data = f.read()
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, "the unprivileged child failed"
    got: dict[str, int] = json.loads(data)
    assert got.pop("uid") == nobody.pw_uid
    return got


@pytest.mark.timeout(120)
def test_modes_hold_under_umask_000_and_another_uid_cannot_connect(spawn, run_dir: Path
                                                                    ) -> None:
    # A world-traversable parent, as runs/ in a deployment: only the run directory guards.
    os.chmod(run_dir.parent, 0o755)
    cfg = write_config(run_dir.parent / "m.yaml", {"source": SMALL, "pools": POOLS})
    with _umask(0):
        p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()
    poll_for(lambda: p.results(), 20, what="a first result")
    assert _mode(run_dir) == 0o700
    socks = sorted(run_dir.glob("*.sock"))
    links = sorted(run_dir.glob("*.link"))
    assert {s.name for s in socks} >= {"control.sock", "heartbeat.sock", "log.sock"}
    assert {s.name for s in links} >= {"capture.link", "workers.link", "results.link"}
    for path in socks + links:
        assert stat.S_ISSOCK(path.stat().st_mode), path
        assert _mode(path) == 0o600, (path.name, oct(_mode(path)))
    for name in ("results.jsonl", "trapflow.log"):
        assert _mode(run_dir / name) == 0o640, (name, oct(_mode(run_dir / name)))

    # The control: a socket nobody may reach where the modes let it (proves the child can
    # connect at all, so a refusal below is the modes' doing).
    open_dir = run_dir.parent / "open"
    open_dir.mkdir()
    os.chmod(open_dir, 0o777)
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.bind(str(open_dir / "probe.sock"))
    os.chmod(open_dir / "probe.sock", 0o777)
    probe.listen(1)
    try:
        targets = [(str(s), socket.SOCK_STREAM) for s in socks]
        targets += [(str(k), socket.SOCK_SEQPACKET) for k in links]
        targets.append((str(open_dir / "probe.sock"), socket.SOCK_STREAM))
        got = _connect_as_nobody(targets)
    finally:
        probe.close()
    assert got.pop(str(open_dir / "probe.sock")) == 0, "the unprivileged child cannot connect"


    assert got and all(e == errno.EACCES for e in got.values()), got
    assert p.status() is not None  # still running, its owner still reaches it
    code, _, err = p.stop()
    assert code == 0, err


@pytest.mark.timeout(120)
def test_tcp_mode_keeps_control_in_the_run_directory_and_status_finds_it(
        spawn, run_dir: Path) -> None:
    base = free_base_port()
    cfg = write_config(run_dir.parent / "t.yaml", {
        "source": SMALL, "pools": POOLS,
        "network": {"transport": "tcp", "base_port": base}})
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    st = p.wait_active()  # `trapflow status --run-dir` only: no config, no port given
    assert st["nodes"]
    assert _mode(run_dir / "control.sock") == 0o600
    with socket.socket() as s:  # nothing answers control on the TCP control port any more
        assert s.connect_ex(("127.0.0.1", base + 6)) != 0
    out = subprocess.run([sys.executable, "-m", "trapflow", "status", "--run-dir",
                          str(run_dir), "--stop"], capture_output=True, text=True,
                         timeout=30, cwd=REPO)
    assert out.returncode == 0, out.stderr
    code, _, err = p.wait(30)
    assert code == 0, err
