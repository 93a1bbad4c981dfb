"""A socket fuzzer against a real pipeline (issue 16, the reliability suite): for about
20 s every bound socket and local link of the run directory gets random frames, random
bytes below ZeroMQ's framing, and the targeted forgeries of items 2, 5 and 7 (forged
answers, a second normalizer, huge and random subscriptions, multi-frame control
requests). Afterwards the pipeline still runs, nothing restarted, no forged line is in
results.jsonl, every processed pair has exactly one line and the ledger adds up."""

from __future__ import annotations

import json
import random
import signal
import socket
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import zmq

from tests import builders
from tests.builders import small_source
from tests.conftest import Pipeline, only_pools, poll_for, write_config
from tests.reliability import figures, scaled
from trapflow.wire import control_msgs, identity, messages
from trapflow.wire.links import Link, LinkClosed, connect_link

pytestmark = pytest.mark.slow  # starts whole pipelines

FUZZ_S = scaled("TRAPFLOW_CHAOS_FUZZ_S", 20.0)  # scripts/chaos.sh runs it longer
SEED = 1616
FORGED = "forged"  # a field no real noop result has


def _node(status: dict[str, Any], name: str) -> dict[str, Any]:
    return next(n for n in status["nodes"] if n["name"] == name)


def _forged_result(seq: int) -> bytes:
    body = messages.Extra(name="noop", fields={FORGED: 1, "gap": 0})
    return messages.encode(builders.result(body, seq=seq, pool="fast"))


class Fuzzer:
    """Peers on every socket and link of one run directory, each sending hostile input."""

    def __init__(self, run_dir: Path, ctx: zmq.Context[zmq.Socket[bytes]], rng: random.Random,
                 real_worker: str) -> None:
        self.dir = run_dir.resolve()
        self.ctx = ctx
        self.rng = rng
        self.real = real_worker
        self.socks: list[zmq.Socket[bytes]] = []
        self.links: dict[str, Link] = {}
        self.sent: Counter[str] = Counter()

    def _sock(self, kind: int, name: str) -> zmq.Socket[bytes]:
        s = self.ctx.socket(kind)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.SNDTIMEO, 100)  # never block the fuzzer on a full queue
        s.connect(f"ipc://{self.dir / name}")
        self.socks.append(s)
        return s

    def close(self) -> None:
        for s in self.socks:
            s.close(linger=0)
        for link in self.links.values():
            link.close()

    def junk(self, n: int = 64) -> bytes:
        return self.rng.randbytes(self.rng.randint(0, n))

    def frames(self) -> list[bytes]:
        return [self.junk() for _ in range(self.rng.randint(1, 6))]

    def _send(self, sock: zmq.Socket[bytes], frames: list[bytes], what: str) -> None:
        try:
            sock.send_multipart(frames)
            self.sent[what] += 1
        except zmq.Again:
            pass

    def _link(self, name: str) -> Link | None:
        link = self.links.get(name)
        if link is None:
            try:
                link = self.links[name] = connect_link(str(self.dir / name))
            except LinkClosed:
                return None
        return link

    def _link_send(self, name: str, frames: list[bytes] | None, what: str,
                   raw: bytes | None = None) -> None:
        link = self._link(name)
        if link is None:
            return
        try:
            if raw is not None:
                link.sock.send(raw)
            elif frames is not None and not link.send(frames):
                return
            self.sent[what] += 1
            while link.recv() is not None:  # whatever comes back (jobs, nothing) is read
                pass
        except (LinkClosed, OSError):
            link.close()
            del self.links[name]  # refused or closed by the broker: reconnect next time

    def below_zmtp(self) -> None:
        """Random bytes where ZeroMQ expects its greeting."""
        name = self.rng.choice(["capture.sock", "workers.sock", "tap.sock", "results-tap.sock",
                                "heartbeat.sock", "control.sock"])
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(0.2)
        try:
            s.connect(str(self.dir / name))
            s.sendall(self.rng.randbytes(self.rng.randint(1, 600)))
            self.sent["below_zmtp"] += 1
        except OSError:
            pass
        finally:
            s.close()

    def setup(self) -> None:
        self.capture = self._sock(zmq.PUSH, "capture.sock")
        self.workers = self._sock(zmq.DEALER, "workers.sock")
        self.heartbeat = self._sock(zmq.PUSH, "heartbeat.sock")
        self.control = self._sock(zmq.DEALER, "control.sock")
        self.xsubs = [self._sock(zmq.XSUB, n) for n in ("tap.sock", "results-tap.sock")]

    def step(self, recent: int) -> None:
        """One hostile message on a randomly chosen target."""
        r = self.rng
        actions: list[Callable[[], None]] = [
            lambda: self._send(self.capture, self.frames(), "capture"),
            lambda: self._send(self.capture, [self.junk(), self.junk(2000), self.junk(2000)],
                               "capture"),
            lambda: self._send(self.workers, self.frames(), "workers"),
            lambda: self._send(self.workers, [messages.encode(messages.Done(
                worker=self.real, pool="fast", seq=recent + r.randint(-5, 20))),
                _forged_result(recent)], "forged_done"),
            lambda: self._send(self.workers, [messages.encode(messages.Gone(
                worker=self.real, reason="forged"))], "forged_gone"),
            # Only the supervisor switches a pool or tells the ladder's level.
            lambda: self._send(self.workers, [messages.encode(r.choice([
                messages.PoolSwitch(pool="fast", active=False),
                messages.PoolSwitch(pool="fast", min_interval_s=100.0)]))], "forged_switch"),
            lambda: self._send(self.workers, [messages.encode(messages.LadderLevel(
                level="vo_health", reason=FORGED))], "forged_level"),
            lambda: self._send(self.heartbeat, self.frames(), "heartbeat"),
            lambda: self._send(self.heartbeat, [b"\x93" + self.junk() + b"\n"], "heartbeat"),
            lambda: self._send(self.control, self.frames(), "control"),
            lambda: self._send(self.control, [b"", messages.encode(control_msgs.StatusRequest()),
                                              *self.frames()], "control_multi"),
            lambda: self._send(r.choice(self.xsubs), [b"\x01" + self.junk(16)], "subscription"),
            lambda: self._send(r.choice(self.xsubs), [b"\x01" + b"x" * (64 << 10)],
                               "huge_subscription"),
            lambda: self._send(r.choice(self.xsubs), self.frames(), "tap"),
            lambda: self._link_send("capture.link", self.frames(), "capture_link"),
            lambda: self._link_send("capture.link", None, "capture_link", raw=self.junk(300)),
            lambda: self._link_send("workers.link", self.frames(), "workers_link"),
            lambda: self._link_send("workers.link", [messages.encode(messages.Done(
                worker=r.choice([self.real, "fuzz"]), pool="fast",
                seq=recent + r.randint(-5, 20))), _forged_result(recent)], "forged_done_link"),
            lambda: self._link_send("results.link", [messages.encode(
                messages.ResultsAck(count=r.randint(-5, 500)))], "second_normalizer"),
            lambda: self._link_send("results.link", self.frames(), "results_link"),
            self.below_zmtp,
        ]
        r.choice(actions)()
        for s in (self.control, *self.xsubs):  # replies and tap traffic: read, dropped
            while s.poll(0):
                s.recv_multipart()


@pytest.mark.timeout(int(160 + FUZZ_S))
def test_fuzz_every_socket_and_link_of_a_running_pipeline(spawn, run_dir: Path, zctx) -> None:
    """Issue 16: a reliability suite that keeps items 2, 5, 7 and 8 true under random input."""
    cfg = write_config(run_dir.parent / "fuzz.yaml", {
        "source": small_source(15.0),
        "pools": only_pools({"fast": {"plugin": "noop", "policy": "ordered:64"}}),
    })
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    st = p.wait_active()
    poll_for(lambda: len(p.results()) > 10, 30, what="first results")
    pids = {n["name"]: n["pid"] for n in st["nodes"]}
    real = identity.worker_identity("fast", 0, pids["worker:fast:0"])
    fuzz = Fuzzer(run_dir, zctx, random.Random(SEED), real)
    fuzz.setup()
    try:
        deadline = time.monotonic() + FUZZ_S
        recent = 0
        n = 0
        while time.monotonic() < deadline:
            if n % 500 == 0:
                recent = max((r["noop"]["seq"] for r in p.results() if "noop" in r), default=0)
            fuzz.step(recent)
            n += 1
            time.sleep(0.0005)
    finally:
        fuzz.close()
    print(f"fuzzer: {n} messages, seed {SEED}: {dict(sorted(fuzz.sent.items()))}")
    assert n > 2000 and len(fuzz.sent) >= 15, fuzz.sent
    # Still running, nothing restarted, still producing.
    st2 = poll_for(lambda: p.status(), 20, what="status after the fuzzing")
    assert all(x["state"] == "active" for x in st2["nodes"]), st2["nodes"]
    assert all(x["restarts"] == 0 for x in st2["nodes"]), st2["nodes"]
    assert {x["name"]: x["pid"] for x in st2["nodes"]} == pids
    assert st2["stats"]["level"] == "full" and st2["stats"]["pools"]["fast"]["active"]
    assert st2["stats"]["pools"]["fast"]["min_interval_s"] == 0.0
    print("broker counters:", _node(st2, "broker")["counters"])
    n0 = len(p.results())
    poll_for(lambda: len(p.results()) > n0 + 20, 30, what="results after the fuzzing")
    code, _, err = p.stop(signal.SIGINT)
    assert code == 0, err
    rows = p.results()
    assert not [r for r in rows if FORGED in json.dumps(r)], "a forged result was written"
    seqs = [r["noop"]["seq"] for r in rows if "noop" in r]
    ledger = json.loads((run_dir / "ledger.json").read_text())
    pool = ledger["pools"]["fast"]
    assert len(seqs) == len(set(seqs)) == pool["processed"] > 100  # each once, none lost
    assert pool["dropped_inactive"] == pool["dropped_by_level"] == 0  # no forged switch
    assert (pool["processed"] + pool["dropped_by_policy"] + pool["timed_out"] + pool["failed"]
            + pool["lost"] + pool.get("unfinished_at_stop", 0)) == ledger["produced"], ledger
    log_lines = (run_dir / "trapflow.log").read_text().count("\n")
    print(f"trapflow.log: {log_lines} lines")
    figures("fuzz", seconds=FUZZ_S, messages=n, kinds=len(fuzz.sent), results=len(seqs),
            duplicates=len(seqs) - len(set(seqs)), lost=pool["lost"],
            restarts=sum(x["restarts"] for x in st2["nodes"]), forged_written=0,
            log_lines=log_lines)
    assert log_lines < 400 * max(1.0, FUZZ_S / 20)  # every per-message warning is rate-limited
