"""Remote worker pools without processes: the remote config and its refusals, key files,
the broker's table of remote workers, the join messages and the worker command's input."""

from __future__ import annotations

import stat
from pathlib import Path
from typing import Any

import msgspec
import pytest
import zmq
import zmq.auth
from click.testing import CliRunner

from trapflow.broker.remote_state import MAX_EVICTED_SHOWN, MAX_REMOTE_WORKERS, RemoteWorkers
from trapflow.broker.trust import local_msg
from trapflow.cli.main import main
from trapflow.config import schema as configmod
from trapflow.errors import ConfigError, ProtocolError, StartupError
from trapflow.pools.remote_worker import config_from
from trapflow.wire import messages
from trapflow.wire.curve import client_keys, server_keys
from trapflow.wire.keys import generate
from trapflow.wire.tap_gate import TapGate
from trapflow.wire.transport import CurveKeys, SocketSpec, open_socket

KEYS = {"server_key": "k/server.key_secret", "authorized_keys": "k/auth"}


@pytest.mark.parametrize("remote,error", [
    ({}, None),
    ({"bind": "tcp://127.0.0.1:5560"}, None),  # loopback may go without keys
    ({"bind": "tcp://localhost:5560"}, None),
    ({"bind": "tcp://[::1]:5560"}, None),
    ({"bind": "tcp://0.0.0.0:5560", **KEYS}, None),
    ({"bind": "tcp://192.168.1.10:5560", **KEYS}, None),
    ({"bind": "tcp://0.0.0.0:5560"}, "beyond loopback needs CURVE keys"),
    ({"bind": "tcp://*:5560"}, "beyond loopback needs CURVE keys"),
    ({"bind": "tcp://10.0.0.1:5560"}, "beyond loopback needs CURVE keys"),
    ({"bind": "tcp://10.0.0.1:5560", "server_key": "s"}, "both server_key and authorized_keys"),
    ({"authorized_keys": "a"}, "both server_key and authorized_keys"),
    ({"bind": "ipc:///tmp/x"}, "expected bind as tcp://HOST:PORT"),
    ({"bind": "tcp://127.0.0.1"}, "expected bind as tcp://HOST:PORT"),
    ({"bind": "tcp://127.0.0.1:80"}, "port in 1024..65535"),
    ({"bind": "tcp://127.0.0.1:5560", "keys": "x"}, "unknown field"),
])
def test_remote_config_binds_beyond_loopback_only_with_keys(remote: dict[str, Any],
                                                            error: str | None) -> None:
    data = {"network": {"remote": remote}}
    if error is None:
        configmod.from_data(data)
        return
    with pytest.raises(ConfigError, match=error) as exc:
        configmod.from_data(data)
    assert "$.network.remote" in str(exc.value)


def test_an_old_tcp_config_still_loads_and_any_remote_port_is_free() -> None:
    """transport tcp once took base_port..base_port+6 (issue 26 item 3 keeps every local
    socket an ipc file): an older config still loads, and no remote port clashes."""
    cfg = configmod.from_data({"network": {"transport": "tcp", "base_port": 5550,
                                           "remote": {"bind": "tcp://127.0.0.1:5553"}}})
    assert cfg.network.remote.bind == "tcp://127.0.0.1:5553"


def test_pipeline_endpoints_still_refuse_non_loopback_hosts() -> None:
    with pytest.raises(ConfigError, match="network.remote.bind"):
        configmod.from_data({"network": {"host": "0.0.0.0", "remote": {
            "bind": "tcp://0.0.0.0:5560", **KEYS}}})


def test_keys_generate_makes_private_loadable_pairs_and_never_overwrites(tmp_path: Path) -> None:
    public, secret = generate(tmp_path / "k", "server")
    for path in (public, secret):
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE((tmp_path / "k").stat().st_mode) == 0o700
    pub, sec = zmq.auth.load_certificate(str(secret))
    assert sec is not None and zmq.curve_public(sec) == pub
    assert server_keys(secret) == CurveKeys(pub, sec)
    assert "secret" not in repr(server_keys(secret))
    with pytest.raises(ConfigError, match="exists"):
        generate(tmp_path / "k", "server")


@pytest.mark.parametrize("name,error", [("", "expected a file name"), ("a/b", "expected a file"),
                                        ("../x", "expected a file name")])
def test_keys_generate_rejects_bad_names(tmp_path: Path, name: str, error: str) -> None:
    with pytest.raises(ConfigError, match=error):
        generate(tmp_path, name)


def test_client_keys_name_the_missing_file(tmp_path: Path) -> None:
    generate(tmp_path, "client")
    with pytest.raises(StartupError, match="server.key, got no such file"):
        client_keys(tmp_path)
    with pytest.raises(StartupError, match="got a public key only"):
        server_keys(tmp_path / "client.key")


def test_curve_sockets_talk_only_with_the_servers_key(tmp_path: Path,
                                                     zctx: zmq.Context[zmq.Socket[bytes]]) -> None:
    """Keys from `generate` set up CURVE through open_socket: the client that knows the
    server's public key is heard."""
    generate(tmp_path / "s", "server")
    generate(tmp_path / "c", "client")
    (tmp_path / "c" / "server.key").write_bytes((tmp_path / "s" / "server.key").read_bytes())
    srv = open_socket(zctx, SocketSpec(zmq.ROUTER, "tcp://127.0.0.1:*", bind=True,
                                       curve=server_keys(tmp_path / "s" / "server.key_secret")))
    endpoint = srv.getsockopt_string(zmq.LAST_ENDPOINT)
    cli = open_socket(zctx, SocketSpec(zmq.DEALER, endpoint, identity=b"w",
                                       curve=client_keys(tmp_path / "c")))
    try:
        cli.send(b"hi")
        assert srv.poll(3000, zmq.POLLIN)
        assert srv.recv_multipart() == [b"w", b"hi"]
        assert srv.getsockopt(zmq.MECHANISM) == zmq.CURVE
    finally:
        cli.close(linger=0)
        srv.close(linger=0)


def test_remote_table_joins_reports_and_bounds_evicted() -> None:
    t = RemoteWorkers()
    assert t.joined(b"far@j:0:1", "j", "far", b"owner@j:9", 0.0)
    assert not t.joined(b"far@j:0:1", "j", "far", b"owner@j:9", 0.5)  # a heartbeat's hello
    assert t.pool_of(b"far@j:0:1") == "far" and t.pool_of(b"x") is None
    assert t.may_report(b"far@j:0:1", b"far@j:0:1")
    assert t.may_report(b"owner@j:9", b"far@j:0:1")
    assert not t.may_report(b"owner@k:9", b"far@j:0:1")  # another host's supervisor
    assert not t.may_report(b"owner@j:9", b"far@j:0:2")  # never said hello
    t.processed(b"far@j:0:1")
    t.processed(b"far@j:0:1")
    [row] = t.stats(2.0, {b"far@j:0:1": "far"})
    assert (row.state, row.processed, row.rate, row.host) == ("active", 2, 1.0, "j")
    t.evicted(b"far@j:0:1", "killed by signal 9")
    [row] = t.stats(1.0, {})
    assert (row.state, row.reason, row.rate) == ("evicted", "killed by signal 9", 0.0)
    for i in range(MAX_EVICTED_SHOWN + 5):
        t.joined(f"far@j:{i}:2".encode(), "j", "far", b"o", 0.0)
        t.evicted(f"far@j:{i}:2".encode(), "gone")
    assert len(t.known) == MAX_EVICTED_SHOWN
    assert set(t.owners) == {b"o"}  # owners of forgotten workers are forgotten too


@pytest.mark.parametrize("live,heard_at,now,forgotten", [
    (False, None, 4.0, 1),  # joined at 0, never ready, silent past liveness 3: forgotten
    (False, None, 2.5, 0),  # within liveness
    (False, 2.0, 4.0, 0),  # it spoke again at 2 (its hello with every heartbeat)
    (True, None, 9.0, 0),  # the broker's worker: its liveness is BrokerState's business
])
def test_stale_remote_entries_are_forgotten(live: bool, heard_at: float | None, now: float,
                                            forgotten: int) -> None:
    """Pins issue 26 item 10: 300 hellos from an authorised key kept 300 entries."""
    t = RemoteWorkers()
    t.joined(b"far@j:0:1", "j", "far", b"o", 0.0)
    if heard_at is not None:
        t.heard(b"far@j:0:1", heard_at)
    assert t.forget_stale(now, 3.0, {b"far@j:0:1": "far"} if live else {}) == forgotten
    assert (len(t.known), t.forgotten) == (1 - forgotten, forgotten)
    assert set(t.owners) == ({b"o"} if not forgotten else set())


def test_the_remote_table_is_capped() -> None:
    t = RemoteWorkers()
    for i in range(MAX_REMOTE_WORKERS):
        assert not t.full(f"far@j:{i}:1".encode())
        t.joined(f"far@j:{i}:1".encode(), "j", "far", b"o", 0.0)
    assert t.full(b"far@j:new:1")
    assert not t.full(b"far@j:0:1")  # a known worker's hello again is no new entry
    t.evicted(b"far@j:0:1", "gone")  # evicted entries are bounded apart (MAX_EVICTED_SHOWN)
    assert not t.full(b"far@j:new:1")


@pytest.mark.parametrize("heard,now,expected", [
    (None, 4.0, []),  # joined at 0, within liveness
    (None, 5.5, [b"far@j:0:1", b"far@j:1:1"]),  # never heard since: host gone
    (3.0, 5.5, []),  # its supervisor's heartbeat came
    (3.0, 8.5, [b"far@j:0:1", b"far@j:1:1"]),
])
def test_workers_of_a_silent_host_are_named(heard: float | None, now: float,
                                            expected: list[bytes]) -> None:
    t = RemoteWorkers()
    for i in range(2):
        t.joined(f"far@j:{i}:1".encode(), "j", "far", b"owner@j:9", 0.0)
    t.joined(b"far@k:0:1", "k", "far", b"owner@k:9", 0.0)
    t.owner_seen(b"owner@k:9", now)  # the other host is fine
    t.owner_seen(b"owner@x:1", now)  # a stranger's heartbeat is not remembered
    if heard is not None:
        t.owner_seen(b"owner@j:9", heard)
    live = {i: "far" for i in t.known}
    assert t.silent(now, 5.0, live) == expected
    assert b"owner@x:1" not in t.owners
    assert t.silent(now, 5.0, {}) == []  # only live workers are evicted


@pytest.mark.parametrize("msg,error", [
    (messages.Hello(worker="far@j:0:1", pool="far", host="j", owner="o"), "local path"),
    (messages.JoinRequest(pool="far", host="j"), "local path"),
    (messages.HostAlive(host="j"), "local path"),
])
def test_join_messages_are_refused_on_local_paths(msg: messages.Msg, error: str) -> None:
    with pytest.raises(ProtocolError, match=error):
        local_msg(messages.decode_worker_msg(messages.encode(msg)))


@pytest.mark.parametrize("data,error", [
    ({"type": "hello", "worker": "w", "pool": "p", "host": "", "owner": "o"}, "length >= 1"),
    ({"type": "hello", "worker": "w" * 129, "pool": "p", "host": "h", "owner": "o"},
     "length <= 128"),
    ({"type": "join_request", "pool": "p"}, "missing required field `host`"),
])
def test_join_message_decoding_is_bounded(data: dict[str, Any], error: str) -> None:
    with pytest.raises(ProtocolError, match=error):
        messages.decode_worker_msg(msgspec.msgpack.encode(data))


RIG = {"width": 320, "height": 240, "fx": 200.0, "fy": 200.0, "cx": 160.0, "cy": 120.0,
       "baseline_m": 0.12}


@pytest.mark.parametrize("pool_config,rig,error", [
    ({"plugin": "digest", "policy": "latest"}, RIG, None),
    ({"plugin": "digest", "policy": "sometimes"}, RIG, "policy"),
    ({"plugin": "digest", "evil": 1}, RIG, "unknown field"),
    ({"plugin": "digest"}, {"width": 320}, "rig"),
])
def test_a_welcome_is_validated_like_the_pipelines_yaml(pool_config: dict[str, Any],
                                                        rig: dict[str, Any],
                                                        error: str | None) -> None:
    w = messages.decode_welcome(messages.encode(messages.Welcome(
        pool="far", plugin="digest", pool_config=pool_config, rig=rig)))
    if error is None:
        cfg, got = config_from(w, "far")
        assert cfg.pools["far"].remote and cfg.pools["far"].count == 1
        assert got.width == 320
        return
    with pytest.raises(ProtocolError, match=error):
        config_from(w, "far")


@pytest.mark.parametrize("args,error", [
    (["--connect", "tcp://10.0.0.1:5560", "--pool", "far"], "expected --keys DIR"),
    (["--connect", "10.0.0.1:5560", "--pool", "far"], "expected tcp://HOST:PORT"),
    (["--connect", "tcp://127.0.0.1:99999", "--pool", "far"], "expected tcp://HOST:PORT"),
    (["--connect", "tcp://127.0.0.1:5560", "--pool", "far", "--keys", "/nonexistent"],
     "no such folder"),
    (["--connect", "tcp://127.0.0.1:5560", "--pool", "far", "--count", "0"], "--count"),
    (["--connect", "tcp://127.0.0.1:5560", "--pool", "not a pool"], "expected a pool name"),
])
def test_worker_command_rejects_bad_input(args: list[str], error: str) -> None:
    res = CliRunner().invoke(main, ["worker", *args])
    assert res.exit_code == 2, res.output
    assert error in res.output


def test_status_lists_remote_workers_with_host_state_and_rate() -> None:
    from trapflow.cli.status_text import format_status

    stats = messages.Stats(t_wall_ns=1, uptime_s=1.0, pairs_in=3, rate_in=1.0, malformed=0,
                           pools={"far": messages.PoolStats(workers=1)}, remote=[
                               messages.RemoteWorker(worker="far@jet:0:7", host="jet",
                                                     pool="far", state="active", processed=4,
                                                     rate=2.5),
                               messages.RemoteWorker(worker="far@jet:1:8", host="jet",
                                                     pool="far", state="evicted",
                                                     reason="killed by signal 9")])
    # As the control socket sends it: JSON, where zero fields of the wire form are absent.
    reply = {"run_dir": "r", "uptime_s": 1.0, "nodes": [],
             "stats": msgspec.json.decode(msgspec.json.encode(
                 {**msgspec.structs.asdict(stats)}))}
    text = format_status(reply)
    rows = [line.split() for line in text.splitlines() if line.startswith("far@")]
    assert rows[0][:6] == ["far@jet:0:7", "jet", "far", "active", "4", "2.5"]
    assert rows[1][:6] == ["far@jet:1:8", "jet", "far", "evicted", "0", "0.0"]
    assert text.rstrip().endswith("killed by signal 9")


@pytest.mark.parametrize("refused_at,calls,want", [
    # Issue 26 item 10: memory libzmq held for refused subscriptions stayed with the process.
    (None, [0.0, 10.0], [False, False]),  # nothing refused: never
    (1.0, [1.0, 2.0, 6.1, 30.0, 61.5], [True, False, True, True, False]),  # 5 s apart, 60 s
])
def test_taps_trim_memory_for_a_while_after_refused_subscriptions(
        refused_at: float | None, calls: list[float], want: list[bool]) -> None:
    gate = TapGate(None, (b"stats",))  # type: ignore[arg-type]  # trim_due reads no socket
    got = []
    for now in calls:
        if refused_at is not None and now == refused_at:
            gate.refused += 1
        got.append(gate.trim_due(now))
    assert got == want
