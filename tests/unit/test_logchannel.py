"""The log channel (LogEntry over a PUSH/PULL in the run directory), the endpoints that stay
in the run directory in TCP mode, the remote port check and the chaos variables."""

from __future__ import annotations

import dataclasses
import logging
import os
import socket
import stat
from pathlib import Path

import msgspec
import pytest

from tests.conftest import poll_for
from tests.reliability import scaled
from trapflow.config.schema import NetworkConfig, RemoteConfig
from trapflow.errors import ProtocolError, StartupError
from trapflow.runtime.logchannel import LogListener, LogSender, PrivateRotatingFile
from trapflow.runtime.ratelog import CONSOLE_ONCE
from trapflow.wire import control_msgs, messages
from trapflow.wire.endpoints import Endpoints, check_ports_free
from trapflow.wire.transport import new_context


class _Collect(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_records_cross_as_structs_with_traceback_and_level(run_dir: Path) -> None:
    run_dir.mkdir()
    ep = Endpoints.for_run(NetworkConfig(), run_dir).log
    ctx = new_context()
    sink = _Collect()
    listener = LogListener(ctx, ep, [sink])
    listener.start()
    sender = LogSender(ep, "worker:mono:1")
    logger = logging.getLogger("tftest.logchannel")
    logger.propagate = False
    logger.addHandler(sender)
    logger.setLevel(logging.DEBUG)
    try:
        logger.warning("pair %d took %s", 7, "100%")  # a % in an argument stays literal
        try:
            raise ValueError("boom")
        except ValueError:
            logger.exception("crashed")
        logger.warning("runs on CPU", extra={CONSOLE_ONCE: True})
        poll_for(lambda: len(sink.records) == 3, 5, what="all three records")
    finally:
        logger.removeHandler(sender)
        sender.close()
        listener.stop()
        ctx.destroy(linger=0)
    first, second, third = sink.records
    assert first.getMessage() == "pair 7 took 100%"
    assert first.levelno == logging.WARNING and first.processName == "worker:mono:1"
    assert first.process == os.getpid() and first.name == "tftest.logchannel"
    assert second.levelno == logging.ERROR
    assert "ValueError: boom" in second.getMessage() and "Traceback" in second.getMessage()
    # Regression: the mark that has the console say a warning once (the ONNX provider line,
    # given by every worker) was lost on the way, and the console said it once per worker.
    assert getattr(third, CONSOLE_ONCE) is True and not getattr(first, CONSOLE_ONCE)
    assert stat.S_IMODE(os.stat(ep[len("ipc://"):]).st_mode) == 0o600


def test_malformed_log_records_are_counted_not_fatal(run_dir: Path, zctx) -> None:
    import zmq

    run_dir.mkdir()
    ep = Endpoints.for_run(NetworkConfig(), run_dir).log
    sink = _Collect()
    listener = LogListener(zctx, ep, [sink])
    listener.start()
    push = zctx.socket(zmq.PUSH)
    push.connect(ep)
    good = messages.encode(control_msgs.LogEntry(name="x", levelno=20, process="p", pid=1,
                                             created=0.0, message="ok"))
    for data in (b"", b"\xc1", b"\x93garbage", messages.encode(control_msgs.StatusRequest()), good):
        push.send(data)
    try:
        poll_for(lambda: sink.records, 5, what="the good record")
    finally:
        push.close(linger=0)
        listener.stop()
    assert listener.malformed == 4
    assert [r.getMessage() for r in sink.records if r.name == "x"] == ["ok"]


@pytest.mark.parametrize(("data", "error"), [
    (b"", "log record"),
    (b"\x81\xa4type\xa3log", "log record"),  # a tag without its fields
    (msgspec.msgpack.encode({"type": "log", "name": 1, "levelno": 20, "process": "p",
                             "pid": 1, "created": 0.0, "message": "m"}), "Expected `str`"),
    (b"\x00" * (messages.MAX_LOG_BYTES + 1), f"at most {messages.MAX_LOG_BYTES} bytes"),
])
def test_decode_log_rejects(data: bytes, error: str) -> None:
    with pytest.raises(ProtocolError, match="log record") as exc:
        control_msgs.decode_log(data)
    assert error in str(exc.value)


def test_every_endpoint_is_an_ipc_file_in_the_run_directory_in_tcp_mode(run_dir: Path
                                                                       ) -> None:
    """Pins issue 26 item 3: transport tcp put capture, workers, taps and heartbeats on
    loopback ports that every local user could reach; now nothing of the pipeline's own is."""
    ep = Endpoints.for_run(NetworkConfig(transport="tcp", base_port=6000), run_dir)
    urls = dataclasses.asdict(ep)
    socks = {n: u for n, u in urls.items() if not n.endswith("_link")}
    assert socks and all(u.startswith(f"ipc://{run_dir.resolve()}/") for u in socks.values()), \
        socks
    assert ep == Endpoints.for_run(NetworkConfig(), run_dir)
    assert ep.control == f"ipc://{run_dir.resolve() / 'control.sock'}"


def test_check_ports_free_names_the_remote_port_a_listener_holds() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        if port < 1024:
            pytest.skip(f"ephemeral port {port} outside remote.bind's range")
        net = NetworkConfig(remote=RemoteConfig(bind=f"tcp://127.0.0.1:{port}"))
        with pytest.raises(StartupError, match=rf":{port} \(network.remote.bind\): address "
                                               "already"):
            check_ports_free(net)
    check_ports_free(NetworkConfig())  # no remote bind: nothing to check
    check_ports_free(NetworkConfig(transport="tcp"))  # nor in the old tcp mode


def test_rotated_log_files_keep_their_mode_under_umask_000(tmp_path: Path) -> None:
    old = os.umask(0)
    try:
        h = PrivateRotatingFile(tmp_path / "t.log", maxBytes=200, backupCount=2)
        rec = logging.makeLogRecord({"msg": "x" * 100, "levelno": 20})
        for _ in range(10):
            h.emit(rec)
        h.close()
    finally:
        os.umask(old)
    files = sorted(tmp_path.glob("t.log*"))
    assert len(files) == 3
    assert {oct(stat.S_IMODE(f.stat().st_mode)) for f in files} == {"0o640"}


@pytest.mark.parametrize(("raw", "error"), [
    ("abc", "expected a number"),
    ("0", "expected a positive number"),
    ("-5", "expected a positive number"),
])
def test_scaled_rejects(monkeypatch: pytest.MonkeyPatch, raw: str, error: str) -> None:
    monkeypatch.setenv("TRAPFLOW_CHAOS_TEST", raw)
    with pytest.raises(ValueError, match=error):
        scaled("TRAPFLOW_CHAOS_TEST", 1.0)


def test_scaled_default_and_value(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TRAPFLOW_CHAOS_TEST", raising=False)
    assert scaled("TRAPFLOW_CHAOS_TEST", 25.0) == 25.0
    monkeypatch.setenv("TRAPFLOW_CHAOS_TEST", "270")
    assert scaled("TRAPFLOW_CHAOS_TEST", 25.0) == 270.0


def test_a_shared_directory_is_refused_as_run_directory(tmp_path: Path) -> None:
    """make_private would otherwise close /tmp (or any sticky shared folder) to everybody."""
    from trapflow.wire.endpoints import make_private

    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o1777)
    with pytest.raises(StartupError, match="expected a directory of this user's own"):
        make_private(shared)
    assert stat.S_IMODE(shared.stat().st_mode) == 0o1777
    make_private(shared / "run")
    assert stat.S_IMODE((shared / "run").stat().st_mode) == 0o700
