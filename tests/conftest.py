"""Shared test harness: short run directories, a pipeline launcher that cleans up after
itself and proves nothing leaked, socket helpers that never block, and poll_for."""

from __future__ import annotations

import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest
import yaml
import zmq

REPO = Path(__file__).resolve().parents[1]
# Every viewer a test starts (in this process or in a child, which inherits it) takes this
# token, as an operator's own (trapflow.viewer.access.TOKEN_ENV); the viewer tests send it.
os.environ.setdefault("TRAPFLOW_VIEWER_TOKEN", secrets.token_urlsafe(24))


def pytest_configure(config: pytest.Config) -> None:
    """Ctrl-C reaches what the tests start. A suite run in the background of a shell
    (`cmd &`) inherits SIGINT and SIGQUIT ignored, and so did every process it started:
    Python keeps an ignored SIGINT ignored, so `trapflow view` and `trapflow record` never
    saw the SIGINT their tests send, and those tests failed only in such runs (SigIgn
    0x1001007 in the view's /proc status). Restored here, in each test process; an exec'd
    child then starts with the default disposition, as from a terminal."""
    for signo, handler in ((signal.SIGINT, signal.default_int_handler),
                           (signal.SIGQUIT, signal.SIG_DFL)):
        if signal.getsignal(signo) == signal.SIG_IGN:
            signal.signal(signo, handler)


def poll_for(predicate: Callable[[], Any], timeout: float, interval: float = 0.05,
             what: str = "condition") -> Any:
    """Call predicate until it returns something truthy; fail after timeout."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


def recv(sock: zmq.Socket[bytes], timeout: float = 2.0) -> list[bytes]:
    """Receive one multipart message or fail after timeout (never blocks forever)."""
    if not sock.poll(int(timeout * 1000), zmq.POLLIN):
        raise AssertionError(f"nothing received within {timeout} s")
    return sock.recv_multipart()


def modem_cli(*args: str) -> subprocess.Popen[bytes]:
    """A modem command (`modem-sim`, `surface`) as a real process; its stderr is kept."""
    cmd = [sys.executable, "-m", "trapflow.cli.modem", *args]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


# The box's sender in the modem tests: fast link, one record per frame, nothing expires.
MODEM_SEND_ARGS = ["--bit-rate", "19200", "--ack-timeout", "0.4", "--no-aggregate", "--no-ttl"]


def run_sender_until(outbox: Path, cfg: Any, done: Callable[[], Any], timeout: float,
                     what: str) -> tuple[float, dict[str, Any]]:
    """The box's sender (a ModemConfig `cfg`) in a thread of this process until done()
    holds: the seconds it took and the sender's stats then."""
    import threading

    from trapflow.modem.sender import ModemSender

    sender = ModemSender(outbox, cfg.port, cfg)
    halt = threading.Event()
    thread = threading.Thread(target=sender.run, args=(halt,))
    thread.start()
    started = time.monotonic()
    try:
        poll_for(done, timeout, what=what)
        return time.monotonic() - started, sender.stats()
    finally:
        halt.set()
        thread.join(timeout=10)


def modem_link(tmp: Path, procs: list[subprocess.Popen[bytes]], seed: int,
               bit_rate: str = "19200", loss: str = "0.1") -> None:
    """The link simulator (latency 0.05 s) between the pseudo-terminals tmp/a (the box's
    end) and tmp/b (the surface's), added to procs, once both ends exist."""
    procs.append(modem_cli(
        "modem-sim", "--bit-rate", bit_rate, "--latency", "0.05", "--loss", loss,
        "--seed", str(seed), "--link-a", str(tmp / "a"), "--link-b", str(tmp / "b")))
    poll_for(lambda: (tmp / "a").exists() and (tmp / "b").exists(), 20,
             what="the simulator's ends")  # fmt: skip


def send_until_drained(outbox: Path, port: Path, procs: list[subprocess.Popen[bytes]],
                       what: str) -> None:
    """Run the box's sender (`modem-send`, 19200 bit/s, no aggregation, no TTL) until every
    record of outbox is acknowledged, then cut its power (SIGKILL)."""
    from trapflow.config.modem import OutboxConfig
    from trapflow.modem.outbox import OutboxQueue

    sender = modem_cli("modem-send", str(outbox), str(port), *MODEM_SEND_ARGS)
    procs.append(sender)
    queue = OutboxQueue(outbox, OutboxConfig())
    try:
        poll_for(lambda: queue.counts()[2] == 0, 40, what=f"{what} to drain")
    finally:
        queue.close()
    sender.send_signal(signal.SIGKILL)  # the box goes down without a word
    sender.wait(timeout=10)


def stop_surface(surface: subprocess.Popen[bytes]) -> dict[str, Any]:
    """Stop `trapflow surface` (SIGTERM): the statistics of its last stderr line."""
    surface.send_signal(signal.SIGTERM)
    _, err = surface.communicate(timeout=10)
    stats: dict[str, Any] = json.loads(err.decode().strip().splitlines()[-1])
    return stats


def surface_idents(out: Path) -> list[int]:
    """The ident (seq) of every record the surface wrote to out, in order."""
    return [next(iter(json.loads(line).values()))["seq"] for line in out.read_text().splitlines()]


@pytest.fixture
def started_procs() -> Iterator[list[subprocess.Popen[bytes]]]:
    """Processes a test starts: killed if still running at the end, reaped, pipes closed."""
    started: list[subprocess.Popen[bytes]] = []
    yield started
    for proc in started:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
        for pipe in (proc.stdout, proc.stderr):
            if pipe is not None:
                pipe.close()


@pytest.fixture
def run_dir() -> Iterator[Path]:
    """A short run directory (ipc socket paths are limited to 107 bytes)."""
    d = Path(tempfile.mkdtemp(prefix="tf-"))
    yield d / "run"
    subprocess.run(["rm", "-rf", str(d)], check=False)


@pytest.fixture
def zctx() -> Iterator[zmq.Context[zmq.Socket[bytes]]]:
    """A context whose sockets must all be closed (linger 0) by the end of the test."""
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    yield ctx
    open_socks = [s for s in ctx._sockets if not s.closed] if hasattr(ctx, "_sockets") else []
    ctx.destroy(linger=0)
    assert not open_socks, f"test left sockets open: {open_socks}"


def write_config(path: Path, data: dict[str, Any]) -> Path:
    """Write a YAML config for a test."""
    path.write_text(yaml.safe_dump(data))
    return path


class TrapflowProcess:
    """A `trapflow` command as a subprocess in its own session, with its descendants
    tracked (`prefix`: a command it runs under, such as `ip netns exec NAME`)."""

    def __init__(self, args: list[str], env: dict[str, str] | None = None,
                 prefix: list[str] | None = None):
        self.proc = subprocess.Popen(
            [*(prefix or []), sys.executable, "-m", "trapflow", *args],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            start_new_session=True, env={**os.environ, **(env or {})}, cwd=REPO,
        )
        self.seen: dict[int, psutil.Process] = {}

    def track(self) -> list[psutil.Process]:
        """Remember every descendant seen so far (to prove later that all are gone)."""
        try:
            kids = psutil.Process(self.proc.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            return []
        for k in kids:
            self.seen.setdefault(k.pid, k)
        return kids

    def wait(self, timeout: float) -> tuple[int, str, str]:
        out, err = self.proc.communicate(timeout=timeout)
        self.ended()
        return self.proc.returncode, out, err

    def ended(self) -> None:
        """Called when the process has exited (subclasses check what it left)."""

    def stop(self, sig: int = signal.SIGINT, timeout: float = 10.0) -> tuple[int, str, str]:
        self.track()
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        return self.wait(timeout)

    def leftovers(self, grace: float = 3.0) -> list[int]:
        """Descendants still running after a short grace (helpers exit right after us)."""
        _gone, alive = psutil.wait_procs(list(self.seen.values()), timeout=grace)
        return [p.pid for p in alive if p.status() != psutil.STATUS_ZOMBIE]

    def kill_all(self) -> None:
        for p in [*self.seen.values()]:
            try:
                p.kill()
            except psutil.NoSuchProcess:
                pass
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)


class Pipeline(TrapflowProcess):
    """A `trapflow start` subprocess in its own session, with its descendants tracked."""

    def __init__(self, args: list[str], run_dir: Path, env: dict[str, str] | None = None):
        self.run_dir = run_dir
        self.config = args[args.index("--config") + 1] if "--config" in args[:-1] else None
        super().__init__(["start", "--run-dir", str(run_dir), *args], env)

    disagreements: list[str] | None = None  # `trapflow check` of a run that ended well

    def ended(self) -> None:
        """A run that ended with exit 0 must tell one story: `trapflow check` of its run
        directory (with its config's file names), as it is the moment it ends (issue 32),
        held by the spawn fixture."""
        if self.disagreements is None and self.proc.returncode == 0 and (
                self.run_dir / "ledger.json").exists():
            from trapflow.config.schema import load
            from trapflow.export.check import check_run

            cfg = load(self.config)
            self.disagreements = check_run(
                self.run_dir, results_file=cfg.normalizer.results_file,
                tracks_file=cfg.observe.tracks_file, counts_file=cfg.observe.counts_file)

    def results(self) -> list[dict[str, Any]]:
        path = self.run_dir / "results.jsonl"
        if not path.exists():
            return []
        lines = path.read_text().splitlines()
        return [json.loads(line) for line in lines if line.strip()]

    def status(self, deadline_s: float = 20.0) -> dict[str, Any] | None:
        """The pipeline's status, or None once it has exited or not answered by deadline_s.

        Asked in this process through the control client `trapflow status` uses (the CLI
        itself is tested in test_cli_surfaces): a fresh interpreter per call cost about a
        second of CPU on every poll. One request may miss its own timeout on a loaded
        machine (a busy supervisor); it is asked again until deadline_s, so a test fails on
        a pipeline that does not answer, not on the machine's load.
        """
        from trapflow.errors import TrapflowError
        from trapflow.wire.control_client import request

        deadline = time.monotonic() + deadline_s
        while True:
            try:
                return request(self.run_dir, "status", 3.0)
            except TrapflowError:
                pass
            if self.proc.poll() is not None or time.monotonic() >= deadline:
                return None
            time.sleep(0.2)

    def wait_active(self, timeout: float = 60.0) -> dict[str, Any]:
        """Poll status until every node is active and stats flow; return that status."""
        def ready() -> dict[str, Any] | None:
            s = self.status()
            if s and s.get("stats") and all(n["state"] == "active" for n in s["nodes"]):
                return s
            return None

        result: dict[str, Any] = poll_for(ready, timeout, interval=0.2, what="every node active")
        return result


def grown(count: Callable[[], int], by: int) -> Callable[[], bool]:
    """A condition for record_until: count() grew by more than `by` since it was first asked
    (when the recorder writes)."""
    start: list[int] = []

    def done() -> bool:
        if not start:
            start.append(count())
        return count() > start[0] + by

    return done


def record_until(run_dir: Path, out: Path, done: Callable[[], Any],
                 timeout: float) -> tuple[int, str]:
    """`trapflow record` of the pipeline running in run_dir into out, stopped (SIGINT) once
    done() holds: its exit status and stderr. done() is first asked once the recorder writes
    (its .part file has bytes): a recorder still starting on a loaded machine would miss what
    done() counts, and a SIGINT before it is up ends it with "Aborted!"."""
    recorder = subprocess.Popen(
        [sys.executable, "-m", "trapflow", "record", "--run-dir", str(run_dir), "-o", str(out)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    part = out.with_name(out.name + ".part")
    try:
        poll_for(lambda: part.exists() and part.stat().st_size > 0, timeout,
                 what="the recorder writing")
        poll_for(done, timeout, what="pairs flowing while recording")
    finally:
        recorder.send_signal(signal.SIGINT)
        _out, err = recorder.communicate(timeout=20)
    return recorder.returncode, err


@pytest.fixture
def spawn(request: pytest.FixtureRequest) -> Iterator[Callable[..., Pipeline]]:
    """Start pipelines; at teardown kill what is left and assert nothing leaked, and that
    every run that ended with exit 0 passes `trapflow check` (a test whose run cannot, says
    why with @pytest.mark.unchecked_run("why"))."""
    started: list[Pipeline] = []

    def _spawn(args: list[str], run_dir: Path, **kw: Any) -> Pipeline:
        p = Pipeline(args, run_dir, **kw)
        started.append(p)
        return p

    yield _spawn
    leaked = []
    for p in started:
        if p.proc.poll() is None:
            p.stop(signal.SIGTERM, timeout=10)
        leaked += p.leftovers()
        p.kill_all()
    assert not leaked, f"processes left behind: {leaked}"
    # Every run that ended well tells one story (`trapflow check`, issue 32).
    told = {str(p.run_dir): p.disagreements for p in started if p.disagreements}
    if request.node.get_closest_marker("unchecked_run") is None:
        assert not told, f"trapflow check found disagreements: {told}"


@pytest.fixture
def prefix() -> Iterator[str]:
    """A shared-memory segment prefix of this test's own; its segments are removed after."""
    from trapflow.wire import frame_ring as fr

    p = f"tftest{secrets.token_hex(3)}-"
    yield p
    for name in fr.list_segments(p):
        os.unlink(os.path.join(fr.SHM_DIR, name))


def only_pools(pools: dict[str, Any]) -> dict[str, Any]:
    """A `pools:` section that runs exactly these pools: a user's pools merge over the default
    pools, so the defaults it does not name are switched off here."""
    from trapflow.config.schema import Config

    return {**{name: {"count": 0} for name in Config().pools if name not in pools}, **pools}


def run_process(args: list[str], timeout: float = 90) -> tuple[int, str, str]:
    """`trapflow process ARGS` in its own session; every process it started must be gone
    after it exits (the LocalCluster's nannies and workers included)."""
    proc = subprocess.Popen([sys.executable, "-m", "trapflow", "process", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, cwd=REPO)
    seen: dict[int, psutil.Process] = {}
    deadline = time.monotonic() + timeout
    try:
        while proc.poll() is None:
            if time.monotonic() > deadline:
                raise TimeoutError(f"trapflow process still running after {timeout} s")
            try:
                for kid in psutil.Process(proc.pid).children(recursive=True):
                    seen.setdefault(kid.pid, kid)
            except psutil.NoSuchProcess:
                pass
            time.sleep(0.1)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)
    _gone, alive = psutil.wait_procs(list(seen.values()), timeout=5)
    left = [p.pid for p in alive if p.status() != psutil.STATUS_ZOMBIE]
    for p in alive:
        p.kill()
    assert not left, f"processes left behind by trapflow process: {left}"
    assert seen, "trapflow process started no worker process"
    return proc.returncode, out, err


def read_lines(path: Path) -> list[dict[str, Any]]:
    """The JSON lines of a results file."""
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()]


def free_base_port() -> int:
    """A base port whose seven consecutive ports are free now."""
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if base + 7 > 65000 or base < 1024:
            continue
        try:
            held = []
            for off in range(7):
                t = socket.socket()
                held.append(t)
                t.bind(("127.0.0.1", base + off))
            return base
        except OSError:
            continue
        finally:
            for t in held:
                t.close()
    pytest.skip("no range of 7 free TCP ports on the loopback")
