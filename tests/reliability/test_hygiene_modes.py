"""Who may enter a running pipeline: modes of the run directory, sockets, links, results and
the log under umask 000, another uid's connections, and everything in TCP mode.

Pins issue 16, item 6: socket and directory modes followed the umask, so under umask 000
an unprivileged local user stopped the pipeline; in TCP mode any local user could, and
`trapflow status --run-dir` could not reach a TCP-mode pipeline at all. Pins issue 26
item 3: TCP mode left frames, pools, pair injection and heartbeats to every local user.
"""

from __future__ import annotations

import errno
import json
import os
import pwd
import shutil
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


# What another local user tries against a TCP-mode pipeline (run by setpriv as `nobody`):
# the ports transport tcp used, and the same sockets as ipc files; it prints what it got.
_ATTACK = r"""
import json, socket, sys, time
import zmq
from tests import builders
from trapflow.wire import messages
base, run = int(sys.argv[1]), sys.argv[2]
out = {"uid": __import__("os").getuid(), "tcp": {}, "frames": 0, "jobs": 0}
for off in range(7):
    with socket.socket() as s:
        s.settimeout(2)
        out["tcp"][str(base + off)] = s.connect_ex(("127.0.0.1", base + off))
def eps(off, name):
    return [f"tcp://127.0.0.1:{base + off}", f"ipc://{run}/{name}"]
ctx = zmq.Context()
sub = ctx.socket(zmq.SUB)
sub.setsockopt(zmq.SUBSCRIBE, b"")
for ep in eps(3, "tap.sock") + eps(4, "results-tap.sock"):
    sub.connect(ep)
join = ctx.socket(zmq.DEALER)
join.setsockopt(zmq.IDENTITY, b"vo:9:1")
for ep in eps(1, "workers.sock"):
    join.connect(ep)
inject = ctx.socket(zmq.PUSH)
beat = ctx.socket(zmq.PUSH)
for ep in eps(0, "capture.sock"):
    inject.connect(ep)
for ep in eps(5, "heartbeat.sock"):
    beat.connect(ep)
deadline = time.monotonic() + 4.0
seq = 10**6
while time.monotonic() < deadline:
    for sock, frames in ((join, [messages.encode(messages.Ready(worker="vo:9:1", pool="vo",
                                                                credit=8))]),
                         (inject, builders.pair_frames(seq)),
                         (beat, [messages.encode(messages.Heartbeat(
                             node="worker:vo:0", pid=1, state="inactive"))])):
        try:
            sock.send_multipart(frames, zmq.NOBLOCK)
        except zmq.Again:
            pass
    seq += 1
    while sub.poll(50):
        sub.recv_multipart()
        out["frames"] += 1
    while join.poll(0):
        join.recv_multipart()
        out["jobs"] += 1
print(json.dumps(out))
ctx.destroy(linger=0)
"""


@pytest.mark.timeout(120)
def test_tcp_mode_gives_another_uid_no_frames_no_pool_no_pairs_no_heartbeats(
        spawn, run_dir: Path) -> None:
    """Pins issue 26 item 3: in TCP mode `nobody` read 18 MB of frames and the results,
    joined a pool and wrote forged lines, injected pairs and forged a worker's heartbeat
    over the loopback ports. Every local socket is now an ipc file in the 0700 run
    directory: the same attempts, as another uid, get nothing and change nothing, and the
    owner still reaches the pipeline with `trapflow status --run-dir` alone."""
    if os.getuid() != 0:
        pytest.skip("needs root to run a client as another uid (setpriv)")
    if shutil.which("setpriv") is None:
        pytest.skip("no setpriv on this host to run a client as another uid")
    try:
        pwd.getpwnam("nobody")
    except KeyError:
        pytest.skip("no user 'nobody' on this host to connect as")
    os.chmod(run_dir.parent, 0o755)  # a world-traversable parent: only the run dir guards
    base = free_base_port()
    cfg = write_config(run_dir.parent / "t.yaml", {
        "source": small_source(30, kind="synthetic"), "pools": POOLS,
        "network": {"transport": "tcp", "base_port": base}})
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    st = p.wait_active()  # `trapflow status --run-dir` only: no config, no port given
    assert st["nodes"]
    poll_for(lambda: p.results(), 30, what="a first result")
    env = {"PATH": os.environ.get("PATH", ""), "PYTHONPATH": os.pathsep.join(
        [str(REPO), *os.environ.get("PYTHONPATH", "").split(os.pathsep)])}
    attack = subprocess.run(
        ["setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups", sys.executable,
         "-c", _ATTACK, str(base), str(run_dir.resolve())],
        capture_output=True, text=True, timeout=60, cwd="/", env=env)
    assert attack.returncode == 0, attack.stderr
    got = json.loads(attack.stdout)
    assert got["uid"] == pwd.getpwnam("nobody").pw_uid
    assert all(code != 0 for code in got["tcp"].values()), got["tcp"]  # no port answers
    assert (got["frames"], got["jobs"]) == (0, 0), got  # no frame read, no pair given
    st2 = p.status()
    assert st2 is not None
    worker = next(n for n in st2["nodes"] if n["name"] == "worker:vo:0")
    assert worker["state"] == "active" and worker["restarts"] == 0, worker
    code, _, err = p.stop()
    assert code == 0, err
    seqs = [row[k]["seq"] for row in p.results() for k in row if isinstance(row[k], dict)
            and "seq" in row[k]]
    assert seqs and max(seqs) < 10**6, "an injected pair was processed"
