"""Forged and hostile messages against a real pipeline: forged answers, a second
normalizer, multi-frame control requests, log floods (issue 16 items 2, 5 and 8), a
worker's result for another pair or pool (issue 26 item 4).

Every forgery goes over the real socket or local link of a running pipeline; each test
checks what reached results.jsonl against the run's own ledger.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest
import zmq

from tests import builders
from tests.builders import small_source
from tests.conftest import Pipeline, only_pools, poll_for, recv, write_config
from tests.reliability import figures, scaled
from trapflow.wire import control_msgs, identity, messages
from trapflow.wire.links import LinkClosed, connect_link

pytestmark = pytest.mark.slow  # starts whole pipelines

SMALL = small_source(15.0)
FORGED = "forged"  # a field no real noop result has
FLOOD = int(scaled("TRAPFLOW_CHAOS_FLOOD", 10_000))  # malformed heartbeats; chaos.sh sends more


def _config(path: Path, **extra: Any) -> Path:
    """One ordered no-op pool: every processed pair is exactly one result line."""
    return write_config(path, {
        "source": SMALL,
        "pools": only_pools({"fast": {"plugin": "noop", "policy": "ordered:64"}}),
        **extra,
    })


def _node(status: dict[str, Any], name: str) -> dict[str, Any]:
    return next(n for n in status["nodes"] if n["name"] == name)


def _forged_result(seq: int) -> bytes:
    body = messages.Extra(name="noop", fields={FORGED: 1, "gap": 0})
    return messages.encode(builders.result(body, seq=seq, pool="fast"))


def _done(worker: str, seq: int) -> bytes:
    return messages.encode(messages.Done(worker=worker, pool="fast", seq=seq))


def _noop_seqs(p: Pipeline) -> list[int]:
    return [row["noop"]["seq"] for row in p.results() if "noop" in row]


def _stop_and_check_ledger(p: Pipeline, run_dir: Path) -> list[dict[str, Any]]:
    """Stop the run; every processed pair has its line, and no line is forged."""
    code, _, err = p.stop(signal.SIGINT)
    assert code == 0, err
    rows = p.results()
    assert not [r for r in rows if FORGED in json.dumps(r)], "a forged result was written"
    processed = json.loads((run_dir / "ledger.json").read_text())["pools"]["fast"]["processed"]
    seqs = _noop_seqs(p)
    assert processed > 20
    assert len(set(seqs)) == processed, (processed, len(set(seqs)))  # nothing lost
    return rows


def _link_refused(link: Any, timeout_s: float = 5.0) -> bool:
    """The broker closed this link: EOF (or a reset) within timeout_s."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if link.wait(100):
            try:
                if link.recv() is None:
                    continue
            except LinkClosed:
                return True
    return False


@pytest.mark.timeout(120)
def test_forged_answers_on_the_workers_socket_and_link_are_never_written(
        spawn, run_dir: Path, zctx) -> None:
    """Issue 16 item 2: a Done with a valid result for a pair never dispatched to its
    sender was written to results.jsonl. Forged here over the workers ROUTER (a stranger
    and a worker's pool name), over the workers link (a stranger's name, and a live
    worker's name taken by a second connection), for pairs never made and pairs in flight."""
    p: Pipeline = spawn(["--config", str(_config(run_dir.parent / "forge.yaml"))], run_dir)
    s = p.wait_active()
    poll_for(lambda: len(p.results()) > 10, 30, what="first results")
    real = identity.worker_identity("fast", 0, _node(s, "worker:fast:0")["pid"])
    dealer = zctx.socket(zmq.DEALER)
    dealer.connect(f"ipc://{run_dir.resolve() / 'workers.sock'}")
    stranger = connect_link(str(run_dir / "workers.link"))
    stranger.send([_done("stranger", 10**6), _forged_result(10**6)])  # names itself first
    impostor = connect_link(str(run_dir / "workers.link"))
    impostor.send([_done(real, 10**6), _forged_result(10**6)])  # a live worker's name: refused
    forged = 1
    deadline = time.monotonic() + 4.0
    while time.monotonic() < deadline:  # pairs just made: some are in flight at the worker
        base = max(_noop_seqs(p), default=0)
        for seq in [*range(base + 1, base + 20), 10**6 + forged, -1]:
            result = _forged_result(seq)
            dealer.send_multipart([_done(real, seq), result])
            dealer.send_multipart([messages.encode(messages.Failed(
                worker=real, pool="fast", seq=seq, reason="forged", kind="Forged"))])
            forged += 2 + stranger.send([_done("stranger", seq), result])  # False: queue full
        time.sleep(0.2)
    assert _link_refused(impostor), "a second link naming a live worker was kept"
    dealer.close(linger=1000)

    def counted() -> dict[str, int] | None:  # counters come with the broker's heartbeats
        st = p.status()
        c: dict[str, int] = _node(st, "broker")["counters"] if st else {}
        n = c.get("rejected_unknown_worker", 0) + c.get("rejected_not_dispatched", 0)
        return c if n >= forged else None

    broker = poll_for(counted, 15, what=f"{forged} forged answers counted")
    assert broker.get("refused_duplicate_worker") == 1, broker
    poll_for(lambda: len(p.results()) > 40, 30, what="results go on")
    stranger.close()
    impostor.close()
    rows = _stop_and_check_ledger(p, run_dir)  # asserts no forged line, nothing lost
    seqs = _noop_seqs(p)
    figures("forged_answers", forged=forged, results=len(rows), forged_written=0, lost=0,
            duplicates=len(seqs) - len(set(seqs)))


@pytest.mark.timeout(120)
def test_a_worker_cannot_attach_a_result_for_another_pair_or_pool(
        spawn, run_dir: Path, zctx) -> None:
    """Issue 26 item 4: the broker checked a Done but forwarded its result unread, so a
    worker could answer a pair it was given with any result (pair 179 answered with a
    stereo "scallop 0.99" for seq 123456789, written). Here a real worker-side DEALER joins
    a pool, takes pairs, and answers them with results naming another seq or pool: none is
    written, each is counted by reason; its one honest answer is written."""
    # The pool's own worker is slow, so the broker gives the joined socket most pairs.
    cfg = write_config(run_dir.parent / "attach.yaml", {"source": SMALL, "pools": only_pools(
        {"fast": {"plugin": "slow", "policy": "fifo:64", "timeout_s": 60.0,
                  "params": {"delay_s": 0.2}}})})
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()
    poll_for(lambda: len(p.results()) > 3, 30, what="first results")
    name = identity.worker_identity("fast", 9, os.getpid())  # a second worker of the pool
    worker = zctx.socket(zmq.DEALER)
    worker.setsockopt(zmq.IDENTITY, name.encode())
    worker.connect(f"ipc://{run_dir.resolve() / 'workers.sock'}")
    try:
        worker.send_multipart([messages.encode(messages.Ready(worker=name, pool="fast",
                                                              credit=7))])
        given = [messages.decode_pair_header(recv(worker, 10)[1]).seq for _ in range(7)]
        claims = [(123456789, "fast"), (given[1] + 1, "fast"), (-5, "fast"),  # another pair
                  (given[3], "mono"), (given[4], "other"), (given[5], "")]  # another pool
        for seq, (named, pool) in zip(given, claims, strict=False):
            body = messages.Extra(name="slow", fields={FORGED: 1, "gap": 0})
            worker.send_multipart([
                messages.encode(messages.Done(worker=name, pool="fast", seq=seq)),
                messages.encode(builders.result(body, seq=named, pool=pool))])
        honest = messages.Extra(name="slow", fields={"honest": 1, "gap": 0})  # the way works
        worker.send_multipart([
            messages.encode(messages.Done(worker=name, pool="fast", seq=given[6])),
            messages.encode(builders.result(honest, seq=given[6], pool="fast"))])

        def counted() -> dict[str, int] | None:  # counters come with the broker's heartbeats
            st = p.status()
            c: dict[str, int] = _node(st, "broker")["counters"] if st else {}
            done = c.get("rejected_result_seq", 0) == 3 and c.get("rejected_result_pool") == 3
            return c if done else None

        poll_for(counted, 15, what="6 foreign results counted")
        poll_for(lambda: [r for r in p.results() if "honest" in json.dumps(r)], 15,
                 what="the honest answer")
    finally:
        worker.close(linger=0)
    code, _, err = p.stop(signal.SIGINT)
    assert code == 0, err
    rows = p.results()
    assert not [r for r in rows if FORGED in json.dumps(r)], "a foreign result was written"
    assert [r["slow"]["seq"] for r in rows if "honest" in r["slow"]] == [given[6]]
    processed = json.loads((run_dir / "ledger.json").read_text())["pools"]["fast"]["processed"]
    assert processed == len({r["slow"]["seq"] for r in rows}) == len(rows)
    text = (run_dir / "trapflow.log").read_text()
    assert "its result names pair 123456789 of pool 'fast'" in text


@pytest.mark.timeout(120)
def test_second_normalizer_is_refused_and_its_acks_lose_nothing(spawn, run_dir: Path) -> None:
    """Issue 16 item 2: any process that connected to the results link replaced the
    normalizer's connection; its acknowledgements made the broker forget unwritten results."""
    p: Pipeline = spawn(["--config", str(_config(run_dir.parent / "norm2.yaml"))], run_dir)
    p.wait_active()
    poll_for(lambda: len(p.results()) > 10, 30, what="first results")
    ack = messages.encode(messages.ResultsAck(count=64))
    refused = 0
    for _ in range(10):
        rogue = connect_link(str(run_dir / "results.link"))
        try:
            for _ in range(5):
                try:
                    rogue.send([ack])  # would make the broker forget 64 unwritten results
                except LinkClosed:
                    break
                time.sleep(0.05)
            refused += _link_refused(rogue)
        finally:
            rogue.close()
    assert refused == 10

    def counted() -> dict[str, Any] | None:  # the broker's counters ride on its heartbeats
        x = p.status()
        n = _node(x, "broker")["counters"].get("refused_second_normalizer", 0) if x else 0
        return x if n >= 10 else None

    st = poll_for(counted, 15, what="10 refused normalizer connections counted")
    assert _node(st, "normalizer")["restarts"] == 0
    n = len(p.results())
    poll_for(lambda: len(p.results()) > n + 20, 30, what="results go on")
    rows = _stop_and_check_ledger(p, run_dir)
    seqs = _noop_seqs(p)
    assert len(seqs) == len(set(seqs)) and len(rows) == len(seqs)  # not one line twice


@pytest.mark.timeout(90)
@pytest.mark.parametrize("kind", ["req", "dealer"])
def test_multi_frame_control_request_gets_an_error_and_the_supervisor_lives(
        spawn, run_dir: Path, zctx, kind: str) -> None:
    """Issue 16 item 5: a two-frame control request killed the supervisor (ZeroMQ EFSM:
    it replied after reading only the first frame), and with it the whole pipeline."""
    p: Pipeline = spawn(["--config", str(_config(run_dir.parent / "ctl.yaml"))], run_dir)
    p.wait_active()
    status = messages.encode(control_msgs.StatusRequest())
    sock = zctx.socket(zmq.REQ if kind == "req" else zmq.DEALER)
    sock.connect(f"ipc://{run_dir.resolve() / 'control.sock'}")
    envelope = [] if kind == "req" else [b""]  # a DEALER writes REQ's empty delimiter itself
    for frames in ([status, b"x"], [status, status, status], [b"junk", b""], [b""] * 50):
        sock.send_multipart([*envelope, *frames])
        reply = recv(sock, 10)[-1]
        assert b"error" in reply and b"control request" in reply, reply
    sock.send_multipart([*envelope, status])  # the socket still answers a good request
    assert json.loads(recv(sock, 10)[-1])["nodes"]
    sock.close(linger=0)
    st = p.status()
    assert st is not None and all(n["state"] == "active" for n in st["nodes"])
    assert p.proc.poll() is None
    code, _, err = p.stop(signal.SIGINT)
    assert code == 0, err


@pytest.mark.timeout(int(100 + FLOOD / 500))
def test_heartbeat_flood_writes_few_lines_and_wire_names_cannot_forge_a_line(
        spawn, run_dir: Path, zctx) -> None:
    """Issue 16 item 8: 10,000 malformed heartbeats wrote 19,511 warning lines, and names
    from the wire were logged raw (a newline in one could forge a log line)."""
    p: Pipeline = spawn(["--config", str(_config(run_dir.parent / "flood.yaml"))], run_dir)
    p.wait_active()
    hb = zctx.socket(zmq.PUSH)
    hb.setsockopt(zmq.SNDTIMEO, 10_000)
    hb.connect(f"ipc://{run_dir.resolve() / 'heartbeat.sock'}")
    rng = __import__("random").Random(16)
    t0 = time.monotonic()
    for i in range(FLOOD):
        hb.send(b"\x93" + rng.randbytes(i % 40) + b"\n\x1b[31mERROR fake\n")
    forger = connect_link(str(run_dir / "workers.link"))
    evil = ("evil\n2026-01-01 00:00:00,000 MainProcess trapflow.supervisor.shell ERROR FAKE LINE"
            "\x1b[2J")
    for seq in range(200):
        forger.send([messages.encode(messages.Done(worker=evil, pool="fast", seq=10**6 + seq)),
                     _forged_result(10**6 + seq)])
    # Status is answered after the heartbeats that wait before it: the flood was read.
    poll_for(lambda: p.status(), 30, what="status after the flood")
    flood_s = time.monotonic() - t0
    hb.close(linger=0)
    forger.close()
    time.sleep(1.0)
    code, _, err = p.stop(signal.SIGINT)
    assert code == 0, err
    text = (run_dir / "trapflow.log").read_bytes().decode()
    lines = text.splitlines()
    hb_lines = [x for x in lines if "malformed heartbeat" in x]
    # One line per 5 s interval (RateLimitedLog), and the one that reports the rest.
    assert 1 <= len(hb_lines) <= flood_s / 5 + 3, (len(hb_lines), flood_s)
    rejected = [x for x in lines if "dropped an answer from worker" in x]
    figures("log_flood", heartbeats=FLOOD, forged_names=200, seconds=round(flood_s, 1),
            warning_lines=len(hb_lines) + len(rejected), log_bytes=len(text), exit=code)
    assert 1 <= len(rejected) <= flood_s / 5 + 3
    assert "evil\\n2026-01-01" in rejected[0]  # escaped, on its own line
    assert not [x for x in lines if "FAKE LINE" in x and "dropped an answer" not in x]
    assert "\x1b" not in text and "fake" not in text.replace("ERROR fake", "")  # no raw bytes
    assert not [x for x in lines if x.startswith("2026-01-01")]


@pytest.mark.timeout(120)
def test_trapflow_log_rotates_at_its_configured_size(spawn, run_dir: Path) -> None:
    """Issue 16 item 8: trapflow.log had no size limit (a chatty plugin wrote 27.8 MB in
    45 s). Four pools logging every pair (`time: true`) fill 64 KiB within seconds."""
    pools = {f"p{i}": {"plugin": "noop", "policy": "fifo:8", "time": True} for i in range(4)}
    cfg = write_config(run_dir.parent / "rot.yaml", {
        "source": {**SMALL, "rate_hz": 30.0}, "pools": only_pools(pools),
        "log_file": {"max_bytes": 65536, "backups": 2},
    })
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    p.wait_active()
    poll_for(lambda: (run_dir / "trapflow.log.2").exists(), 60, interval=0.5,
             what="the second rotation")
    time.sleep(1.0)
    code, _, err = p.stop(signal.SIGINT)
    assert code == 0, err
    logs = sorted(run_dir.glob("trapflow.log*"))
    assert [x.name for x in logs] == ["trapflow.log", "trapflow.log.1", "trapflow.log.2"]
    for path in logs:
        assert path.stat().st_size <= 65536, (path.name, path.stat().st_size)
    assert "pair" in (run_dir / "trapflow.log.1").read_text()  # the plugin's lines rotated
    assert os.path.getsize(run_dir / "trapflow.log.2") > 60000  # full before it rotated
