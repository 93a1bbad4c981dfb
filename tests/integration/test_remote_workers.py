"""Worker pools on another host: `trapflow worker` processes join a running pipeline over
tcp with CURVE keys, give the same results as local workers, unauthorised clients are
refused and counted, a kill -9 loses only the dead process's pairs, and (where this
machine lets a test make a network namespace) the link is a real non-loopback one."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest

from tests.builders import small_source
from tests.conftest import Pipeline, TrapflowProcess, only_pools, poll_for, write_config
from trapflow.wire.keys import generate

pytestmark = pytest.mark.slow  # starts whole pipelines

SMALL = small_source(None, seed=3)
DETECTOR = "tests.integration.remote_plugins:PooledDetector"


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        port: int = s.getsockname()[1]
        return port


@pytest.fixture
def keys(tmp_path: Path) -> dict[str, Path]:
    """A pipeline key pair, an authorised worker's folder and an unauthorised one's."""
    generate(tmp_path / "pipeline", "server")
    authorized = tmp_path / "authorized"
    authorized.mkdir()
    for who in ("worker", "stranger"):
        folder = tmp_path / who
        generate(folder, "client")
        shutil.copy(tmp_path / "pipeline" / "server.key", folder / "server.key")
    shutil.copy(tmp_path / "worker" / "client.key", authorized / "worker.key")
    return {"server_key": tmp_path / "pipeline" / "server.key_secret",
            "authorized": authorized, "worker": tmp_path / "worker",
            "stranger": tmp_path / "stranger"}


def remote_config(path: Path, bind: str, keys: dict[str, Path], pools: dict[str, Any],
                  source: dict[str, Any]) -> Path:
    return write_config(path, {
        "source": source,
        "network": {"remote": {"bind": bind, "server_key": str(keys["server_key"]),
                               "authorized_keys": str(keys["authorized"])}},
        "pools": only_pools(pools),
    })


class RemoteWorker(TrapflowProcess):
    """A `trapflow worker` process (a small supervisor and its worker processes)."""

    def __init__(self, args: list[str], prefix: list[str] | None = None) -> None:
        super().__init__(["worker", *args], prefix=prefix)

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 15.0) -> tuple[int, str, str]:
        return super().stop(sig, timeout)


@pytest.fixture
def remote() -> Iterator[Callable[..., RemoteWorker]]:
    """Start `trapflow worker` processes; at teardown stop them and assert none is left."""
    started: list[RemoteWorker] = []

    def _start(*args: str, prefix: list[str] | None = None) -> RemoteWorker:
        w = RemoteWorker(list(args), prefix)
        started.append(w)
        return w

    yield _start
    left = []
    for w in started:
        if w.proc.poll() is None:
            try:
                w.stop()
            except subprocess.TimeoutExpired:
                pass  # kill_all kills it
        left += w.leftovers()
        w.kill_all()
    assert not left, f"remote worker processes left behind: {left}"


def remote_rows(p: Pipeline, pool: str) -> list[dict[str, Any]]:
    s = p.status()
    if not s or not s.get("stats"):
        return []
    return [r for r in s["stats"].get("remote", []) if r["pool"] == pool]


def broker_counters(p: Pipeline) -> dict[str, int]:
    s = p.status() or {"nodes": []}
    return next((n["counters"] for n in s["nodes"] if n["name"] == "broker"), {})


@pytest.mark.timeout(150)
def test_remote_workers_over_curve_give_the_same_results_as_local_ones(
        spawn: Callable[..., Pipeline], remote: Callable[..., RemoteWorker], run_dir: Path,
        keys: dict[str, Path]) -> None:
    """The crab detector (ONNX) and a pixel digest run in a local pool and in a remote pool
    of two `trapflow worker` processes over tcp with CURVE: for every pair both saw, the
    detections and the pixels are identical, and the remote results name remote workers."""
    bind = f"tcp://127.0.0.1:{free_port()}"
    cfg = remote_config(run_dir.parent / "same.yaml", bind, keys, {
        "near": {"plugin": DETECTOR, "policy": "ordered:64"},
        "far": {"plugin": DETECTOR, "policy": "ordered:64", "count": 0, "remote": True},
        "near_px": {"plugin": "digest", "policy": "ordered:64"},
        "far_px": {"plugin": "digest", "policy": "ordered:64", "count": 0, "remote": True},
    }, {**SMALL, "rate_hz": 4.0, "encoding": "jpeg"})
    p = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()
    remote("--connect", bind, "--pool", "far", "--count", "2", "--keys", str(keys["worker"]),
           "--name", "jetson")
    remote("--connect", bind, "--pool", "far_px", "--keys", str(keys["worker"]))
    poll_for(lambda: len([r for r in remote_rows(p, "far") if r["state"] == "active"]) == 2
             and remote_rows(p, "far_px"), 40, interval=0.5, what="three remote workers active")
    poll_for(lambda: len({r["pooled"]["seq"] for r in p.results() if "pooled" in r
                          and r["pooled"]["pool"] == "far"}) >= 20, 60, interval=0.5,
             what="20 pairs detected remotely")
    rows = remote_rows(p, "far")
    assert {r["host"] for r in rows} == {"jetson"}
    code, _, err = p.stop(signal.SIGINT, timeout=20)
    assert code == 0, err
    dets: dict[str, dict[int, Any]] = defaultdict(dict)
    px: dict[str, dict[int, str]] = defaultdict(dict)
    workers: dict[str, set[str]] = defaultdict(set)
    for row in p.results():
        if "pooled" in row:
            r = row["pooled"]
            dets[r["pool"]][r["seq"]] = r["detections"]
            workers[r["pool"]].add(r["worker"])
        elif "digest" in row:
            px[row["digest"]["pool"]][row["digest"]["seq"]] = row["digest"]["sha1"]
    common = set(dets["near"]) & set(dets["far"])
    assert len(common) >= 20
    assert all(dets["near"][s] == dets["far"][s] for s in common), [
        (s, dets["near"][s], dets["far"][s]) for s in common if dets["near"][s] != dets["far"][s]]
    assert sum(len(dets["far"][s]) for s in common) > 0  # the detector did find crabs
    assert all("@jetson:" in w for w in workers["far"]) and len(workers["far"]) == 2
    assert all("@" not in w for w in workers["near"])
    common_px = set(px["near_px"]) & set(px["far_px"])
    assert len(common_px) >= 20
    assert all(px["near_px"][s] == px["far_px"][s] for s in common_px)


@pytest.mark.timeout(120)
def test_raw_pairs_reach_a_remote_worker_as_jpeg_of_the_same_pixels(
        spawn: Callable[..., Pipeline], remote: Callable[..., RemoteWorker], run_dir: Path,
        keys: dict[str, Path]) -> None:
    """Raw pairs in the ring reach a remote worker as JPEG, encoded once by the broker (a
    raw 1280x720 pair is 5.5 MB, too much for the link to a compute box): the same pictures
    as a local worker of the shared-memory ring sees, pair for pair, within JPEG's loss."""
    bind = f"tcp://127.0.0.1:{free_port()}"
    cfg = remote_config(run_dir.parent / "raw.yaml", bind, keys, {
        "near_px": {"plugin": "digest", "policy": "ordered:64"},
        "far_px": {"plugin": "digest", "policy": "ordered:64", "count": 0, "remote": True},
    }, {**SMALL, "rate_hz": 10.0, "encoding": "raw"})
    p = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()
    remote("--connect", bind, "--pool", "far_px", "--keys", str(keys["worker"]))
    poll_for(lambda: [r for r in remote_rows(p, "far_px") if r.get("processed", 0) >= 30], 40,
             interval=0.5, what="30 raw pairs processed remotely")
    code, _, err = p.stop(signal.SIGINT, timeout=20)
    assert code == 0, err
    px: dict[str, dict[int, dict[str, Any]]] = defaultdict(dict)
    for row in p.results():
        if "digest" in row:
            d = row["digest"]
            assert d["shape"] == [240, 320, 3]
            px[d["pool"]][d["seq"]] = d
    common = set(px["near_px"]) & set(px["far_px"])
    assert len(common) >= 30
    for s in common:
        near, far = px["near_px"][s], px["far_px"][s]
        assert (near["encoding"], far["encoding"]) == ("raw", "jpeg"), (near, far)
        assert abs(near["mean"] - far["mean"]) < 2.0, (s, near, far)
    assert len({px["far_px"][s]["sha1"] for s in common}) > len(common) // 2  # pixels change


@pytest.mark.timeout(120)
@pytest.mark.parametrize("who,refusal", [
    ("plain", "refused_remote_bad_handshake"),  # no CURVE at all
    ("stranger", "refused_remote_unauthorised_key"),  # a key not in authorized_keys
])
def test_unauthorised_clients_are_refused_and_counted(
        spawn: Callable[..., Pipeline], remote: Callable[..., RemoteWorker], run_dir: Path,
        keys: dict[str, Path], who: str, refusal: str) -> None:
    """A worker without keys, or with a key the pipeline does not know, never joins: it
    gives up with the reason, the broker counts the refused handshakes, nothing reaches it."""
    bind = f"tcp://127.0.0.1:{free_port()}"
    cfg = remote_config(run_dir.parent / "auth.yaml", bind, keys, {
        "far": {"plugin": "digest", "policy": "latest", "count": 0, "remote": True},
    }, {**SMALL, "rate_hz": 5.0})
    p = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()
    args = ["--connect", bind, "--pool", "far", "--timeout", "4"]
    if who == "stranger":
        args += ["--keys", str(keys["stranger"])]
    w = remote(*args)
    code, _, err = w.wait(timeout=30)  # it gives up by itself after --timeout
    assert code == 2, err
    assert "no answer from the pipeline" in err and "authorized_keys" in err
    counters = poll_for(lambda: (c := broker_counters(p)) and c.get(refusal, 0) >= 1 and c,
                        10, interval=0.3, what=f"{refusal} counted")
    assert counters[refusal] >= 1
    s = poll_for(p.status, 5, what="status")
    assert s["stats"]["pools"]["far"]["workers"] == 0
    assert s["stats"]["pools"]["far"]["processed"] == 0
    assert not s["stats"].get("remote")
    code, _, err = p.stop(signal.SIGINT, timeout=20)
    assert code == 0, err


@pytest.mark.timeout(150)
def test_kill_9_of_a_remote_worker_loses_only_its_pairs_and_the_pool_goes_on(
        spawn: Callable[..., Pipeline], remote: Callable[..., RemoteWorker], run_dir: Path,
        keys: dict[str, Path]) -> None:
    """A remote worker process killed with SIGKILL while it holds a pair: its supervisor
    reports it at once, the pair is counted lost (not timed out), only that one; the
    supervisor starts another that joins; the pool's local worker never stops."""
    bind = f"tcp://127.0.0.1:{free_port()}"
    cfg = remote_config(run_dir.parent / "kill.yaml", bind, keys, {
        "far": {"plugin": "slow", "policy": "latest", "count": 1, "remote": True,
                "params": {"delay_s": 1.0}, "timeout_s": 60.0},
    }, {**SMALL, "rate_hz": 5.0})
    p = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()
    w = remote("--connect", bind, "--pool", "far", "--keys", str(keys["worker"]),
               "--name", "jetson")
    first = poll_for(lambda: [r for r in remote_rows(p, "far") if r["state"] == "active"
                              and r.get("processed", 0) >= 1], 40, interval=0.3,
                     what="the remote worker processing")[0]
    victim = int(first["worker"].rsplit(":", 1)[1])
    assert victim in [k.pid for k in w.track()]
    poll_for(lambda: (s := p.status()) and s["stats"]["pools"]["far"]["in_flight"] == 2, 10,
             interval=0.05, what="both workers (local, remote) holding a pair")
    os.kill(victim, signal.SIGKILL)
    evicted = poll_for(lambda: [r for r in remote_rows(p, "far")
                                if r["worker"] == first["worker"] and r["state"] == "evicted"],
                       10, interval=0.2, what="the killed worker evicted")[0]
    assert "signal 9" in evicted["reason"]
    before = poll_for(p.status, 5, what="status")["stats"]["pools"]["far"]
    assert before["lost"] == 1 and before["timed_out"] == 0
    poll_for(lambda: [r for r in remote_rows(p, "far") if r["state"] == "active"
                      and r["worker"] != first["worker"] and r.get("processed", 0) >= 1],
             40, interval=0.5, what="a restarted remote worker processing")
    after = poll_for(p.status, 5, what="status")["stats"]["pools"]["far"]
    assert after["processed"] > before["processed"]
    assert after["lost"] == 1 and after["timed_out"] == 0
    code, out, err = w.stop()
    assert code == 0, err
    code, _, err = p.stop(signal.SIGINT, timeout=20)
    assert code == 0, err


@pytest.mark.timeout(150)
def test_remote_workers_rejoin_a_broker_restarted_after_kill_9(
        spawn: Callable[..., Pipeline], remote: Callable[..., RemoteWorker], run_dir: Path,
        keys: dict[str, Path]) -> None:
    """The pipeline's side dies: the broker killed with SIGKILL is restarted by the
    supervisor and binds the remote port again; the same remote worker process (no
    restart on its host) joins the new broker by its next heartbeat's hello and goes on."""
    bind = f"tcp://127.0.0.1:{free_port()}"
    cfg = remote_config(run_dir.parent / "broker.yaml", bind, keys, {
        "far": {"plugin": "digest", "policy": "latest", "count": 0, "remote": True},
    }, {**SMALL, "rate_hz": 5.0})
    p = spawn(["--config", str(cfg)], run_dir)
    st = p.wait_active()
    broker = next(n["pid"] for n in st["nodes"] if n["name"] == "broker")
    w = remote("--connect", bind, "--pool", "far", "--keys", str(keys["worker"]))
    first = poll_for(lambda: [r for r in remote_rows(p, "far") if r.get("processed", 0) >= 3],
                     40, interval=0.3, what="the remote worker processing")[0]
    os.kill(broker, signal.SIGKILL)
    poll_for(lambda: (s := p.status()) and any(
        n["name"] == "broker" and n["pid"] != broker and n["state"] == "active"
        for n in s["nodes"]), 30, interval=0.3, what="a new broker")
    again = poll_for(lambda: [r for r in remote_rows(p, "far") if r.get("processed", 0) >= 3
                              and r["state"] == "active"], 30, interval=0.3,
                     what="the remote worker processing for the new broker")[0]
    assert again["worker"] == first["worker"]  # the same process: it was never restarted
    code, _, err = w.stop()
    assert code == 0, err
    code, _, err = p.stop(signal.SIGINT, timeout=20)
    assert code == 0, err


@pytest.mark.timeout(150)
def test_a_silent_host_loses_its_workers_pairs_and_they_rejoin_when_it_wakes(
        spawn: Callable[..., Pipeline], remote: Callable[..., RemoteWorker], run_dir: Path,
        keys: dict[str, Path]) -> None:
    """A host that stops answering (every `trapflow worker` process stopped with SIGSTOP,
    as a Jetson that hangs or loses power): after the liveness its workers are evicted and
    the pair one held is lost, not left to time out; woken, they join again."""
    bind = f"tcp://127.0.0.1:{free_port()}"
    cfg = remote_config(run_dir.parent / "silent.yaml", bind, keys, {
        "far": {"plugin": "slow", "policy": "latest", "count": 0, "remote": True,
                "params": {"delay_s": 0.5}, "timeout_s": 120.0},
    }, {**SMALL, "rate_hz": 5.0})
    p = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()
    w = remote("--connect", bind, "--pool", "far", "--keys", str(keys["worker"]))
    first = poll_for(lambda: [r for r in remote_rows(p, "far") if r.get("processed", 0) >= 2],
                     40, interval=0.3, what="the remote worker processing")[0]
    poll_for(lambda: (s := p.status()) and s["stats"]["pools"]["far"]["in_flight"] == 1, 10,
             interval=0.05, what="the remote worker holding a pair")
    tree = [psutil.Process(w.proc.pid), *w.track()]
    for proc in tree:
        proc.suspend()
    try:
        row = poll_for(lambda: [r for r in remote_rows(p, "far") if r["state"] == "evicted"],
                       20, interval=0.3, what="the silent host's worker evicted")[0]
        assert row["worker"] == first["worker"] and "silent" in row["reason"]
        far = poll_for(p.status, 5, what="status")["stats"]["pools"]["far"]
        assert far["lost"] == 1 and far["timed_out"] == 0 and far["workers"] == 0
    finally:
        for proc in tree:
            proc.resume()
    poll_for(lambda: [r for r in remote_rows(p, "far") if r["state"] == "active"
                      and r.get("processed", 0) > first.get("processed", 0) + 1], 30,
             interval=0.3, what="the woken worker processing again")
    code, _, err = w.stop()
    assert code == 0, err
    code, _, err = p.stop(signal.SIGINT, timeout=20)
    assert code == 0, err


NETNS = "tf-remote-test"
VETH_HOST, VETH_NS = "tfr0", "tfr1"
HOST_IP, NS_IP = "10.231.77.1", "10.231.77.2"


def _netns_unavailable() -> str | None:
    if not sys.platform.startswith("linux"):
        return "network namespaces are Linux only"
    if os.geteuid() != 0:
        return "creating a network namespace and a veth pair needs root"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    return None


@pytest.fixture
def netns() -> Iterator[str]:
    """A network namespace joined to this one by a veth pair (10.231.77.1 <-> .2)."""
    why = _netns_unavailable()
    if why:
        pytest.skip(why)
    subprocess.run(["ip", "netns", "del", NETNS], capture_output=True, check=False)
    steps = [["ip", "netns", "add", NETNS],
             ["ip", "link", "add", VETH_HOST, "type", "veth", "peer", "name", VETH_NS],
             ["ip", "link", "set", VETH_NS, "netns", NETNS],
             ["ip", "addr", "add", f"{HOST_IP}/24", "dev", VETH_HOST],
             ["ip", "link", "set", VETH_HOST, "up"],
             ["ip", "netns", "exec", NETNS, "ip", "addr", "add", f"{NS_IP}/24", "dev", VETH_NS],
             ["ip", "netns", "exec", NETNS, "ip", "link", "set", VETH_NS, "up"],
             ["ip", "netns", "exec", NETNS, "ip", "link", "set", "lo", "up"]]
    try:
        for step in steps:
            done = subprocess.run(step, capture_output=True, text=True, check=False)
            if done.returncode != 0:
                pytest.skip(f"this machine does not allow a network namespace: "
                            f"{' '.join(step)}: {done.stderr.strip()}")
        yield NETNS
    finally:
        subprocess.run(["ip", "netns", "del", NETNS], capture_output=True, check=False)
        subprocess.run(["ip", "link", "del", VETH_HOST], capture_output=True, check=False)


@pytest.mark.timeout(150)
def test_a_worker_in_another_network_namespace_joins_over_a_real_link(
        spawn: Callable[..., Pipeline], remote: Callable[..., RemoteWorker], run_dir: Path,
        keys: dict[str, Path], netns: str) -> None:
    """The pipeline binds a non-loopback address (allowed with keys only); a worker in its
    own network namespace reaches it over a veth pair and processes pairs."""
    bind = f"tcp://{HOST_IP}:{free_port(HOST_IP)}"
    cfg = remote_config(run_dir.parent / "netns.yaml", bind, keys, {
        "far": {"plugin": "digest", "policy": "latest", "count": 0, "remote": True},
    }, {**SMALL, "rate_hz": 5.0})
    p = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()
    w = remote("--connect", bind, "--pool", "far", "--keys", str(keys["worker"]),
               "--name", "namespace", prefix=["ip", "netns", "exec", netns])
    row = poll_for(lambda: [r for r in remote_rows(p, "far") if r.get("processed", 0) >= 5],
                   40, interval=0.5, what="the namespaced worker processing")[0]
    assert row["host"] == "namespace" and row["state"] == "active"
    inside = subprocess.run(["ip", "netns", "identify", str(w.track()[0].pid)],
                            capture_output=True, text=True, check=False)
    assert inside.stdout.strip() == netns
    code, _, err = w.stop()
    assert code == 0, err
    code, _, err = p.stop(signal.SIGINT, timeout=20)
    assert code == 0, err


@pytest.mark.timeout(150)
def test_a_remote_hosts_recycled_workers_are_replaced_at_once_without_loss(
        spawn: Callable[..., Pipeline], remote: Callable[..., RemoteWorker], run_dir: Path,
        keys: dict[str, Path]) -> None:
    """`trapflow worker` on another host: its workers take max_jobs from the pipeline's
    pool config, say goodbye when they reach it, and its small supervisor replaces them at
    once (no back-off, no warning); the broker loses none of their pairs. Pins a loss: the
    broker's answer to a worker's last Done went to a DEALER already gone (EHOSTUNREACH)
    before it read that worker's goodbye, queued behind the Done; the pair was counted lost
    ("unreachable") with a warning. It now reads the socket before it judges the send."""
    bind = f"tcp://127.0.0.1:{free_port()}"
    cfg = remote_config(run_dir.parent / "far.yaml", bind, keys, {
        "far": {"plugin": "noop", "policy": "fifo:8", "count": 0, "remote": True,
                "max_jobs": 3},
    }, small_source(10.0))
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()
    w = remote("--connect", bind, "--pool", "far", "--keys", str(keys["worker"]))

    def recycled_twice() -> list[dict[str, Any]] | None:
        rows = remote_rows(p, "far")
        gone = [r for r in rows if r["state"] == "evicted"]
        ok = len(gone) >= 2 and all(r.get("reason", "").startswith("recycled:jobs") for r in gone)
        return rows if ok else None

    poll_for(recycled_twice, 60, interval=0.5, what="two remote workers recycled")
    code, out, werr = w.stop()
    assert code == 0, werr
    code, _, err = p.stop(signal.SIGINT, timeout=20)
    assert code == 0, err
    pool = json.loads((run_dir / "ledger.json").read_text())["pools"]["far"]
    assert pool["lost"] == 0 and pool["processed"] >= 6, pool
    assert "restarting in" not in werr, werr  # replaced at once, not after a back-off
    assert "WARNING" not in werr, werr
