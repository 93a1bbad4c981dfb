"""Keeping workers healthy (issue 14 part 6): workers recycled past their pool's max_rss_mb
or max_jobs are replaced without losing a pair or spending the restart budget, and a
worker that leaves on purpose is no warning in the broker's log."""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests import builders
from tests.builders import small_source
from tests.conftest import Pipeline, only_pools, write_config
from trapflow.broker.node import BrokerNode
from trapflow.config.schema import Config, PoolConfig
from trapflow.runtime.node import NodeSpec
from trapflow.wire import identity, messages
from trapflow.wire.endpoints import make_private
from trapflow.wire.frame_ring import FrameRing
from trapflow.wire.links import LinkClient

pytestmark = pytest.mark.slow  # starts whole pipelines

SMALL = small_source(15.0)
GROW = "tests.integration.recycle_plugins:Grow"


def _warnings(text: str) -> list[str]:
    """WARNING lines, but for the one about a segment another run left in /dev/shm (this
    machine's past, not this run's doing)."""
    return [line for line in text.splitlines()
            if "WARNING" in line and "stale shared-memory segment" not in line]


def _ledger(run_dir: Path) -> dict:
    data: dict = json.loads((run_dir / "ledger.json").read_text())
    return data


@contextlib.contextmanager
def _broker_with_link(run_dir: Path, prefix: str
                      ) -> Iterator[tuple[BrokerNode, LinkClient, Any, Any]]:
    """A broker of one `noop` pool (fifo:8) over a real ring, and one worker link it has
    accepted: (broker, client, the worker's end of the link, the broker's end)."""
    make_private(run_dir)
    cfg = Config(pools={"noop": PoolConfig(plugin="noop", policy="fifo:8")})
    ring = FrameRing.create(8, 64 * 48 * 3 * 2, prefix=prefix)
    broker = BrokerNode(NodeSpec("broker", "broker", cfg, run_dir, ring=ring.name))
    client = LinkClient(broker.endpoints.workers_link)
    try:
        link = client.get()
        assert link is not None
        (served,) = broker.accept("worker")  # the step the loop takes on a readable listener
        yield broker, client, link, served
    finally:
        client.drop()
        broker.close()
        ring.close()


@pytest.mark.timeout(60)
def test_broker_reads_a_recycled_workers_goodbye_before_it_calls_a_send_news(
        run_dir: Path, prefix: str, caplog: pytest.LogCaptureFixture) -> None:
    """Pins the broker's "cannot reach worker ...: Broken pipe" warning at a normal stop: a
    worker answered its last pair, said goodbye and closed its link before the broker read
    the answer; the answer gave it a credit back, the broker sent it the next pair into the
    closed link, warned and counted that pair lost. Now the broker reads the goodbye waiting
    on the link first: the pair is queued again (not lost) and the log says it at debug."""
    with _broker_with_link(run_dir, prefix) as (broker, client, link, served):
        ident = identity.worker_identity("noop", 0, 4242)
        link.send([messages.encode(messages.Ready(worker=ident, pool="noop", credit=1))])
        broker._drain_link(served)
        broker._on_capture(builders.pair_frames(0))  # dispatched to the worker
        broker._on_capture(builders.pair_frames(1))  # pending: its one credit is taken
        job = link.recv()
        assert job is not None and messages.decode_job(job[0]).pool == "noop"
        result = builders.result(messages.Extra(name="noop", fields={}), seq=0, pool="noop")
        link.send([messages.encode(messages.Done(worker=ident, pool="noop", seq=0)),
                   messages.encode(result)])
        link.send([messages.encode(messages.Gone(
            worker=ident, reason=messages.recycled_reason("jobs")))])
        client.drop()  # the worker exits before the broker reads any of it
        with caplog.at_level(logging.DEBUG, logger="trapflow.broker.node"):
            broker._drain_link(served)
        st = broker.state.pool_stats()["noop"]
        assert (st.processed, st.lost, st.pending, st.in_flight) == (1, 0, 1, 0)
        assert broker.state.worker_pools() == {}
        warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        assert warned == []
        assert any("which is leaving" in r.getMessage() for r in caplog.records)
        assert broker.unroutable == 1  # the send did fail: this is the path pinned


@pytest.mark.timeout(60)
def test_the_supervisors_notice_of_a_recycle_does_not_overtake_the_workers_answer(
        run_dir: Path, prefix: str, caplog: pytest.LogCaptureFixture) -> None:
    """The supervisor tells the broker of a recycled worker's exit on the workers socket,
    which the broker reads before the local links: under load its notice came first, the
    goodbye pair went back to the queue and the worker's answer, read next, was refused as
    from an unknown worker (a warning, the result dropped, the pair computed twice). The
    broker now reads that worker's link before it applies the notice."""
    with _broker_with_link(run_dir, prefix) as (broker, client, link, served):
        ident = identity.worker_identity("noop", 0, 4343)
        link.send([messages.encode(messages.Ready(worker=ident, pool="noop", credit=1))])
        broker._drain_link(served)
        broker._on_capture(builders.pair_frames(0))
        assert link.recv() is not None
        result = builders.result(messages.Extra(name="noop", fields={}), seq=0, pool="noop")
        link.send([messages.encode(messages.Done(worker=ident, pool="noop", seq=0)),
                   messages.encode(result)])
        link.send([messages.encode(messages.Gone(
            worker=ident, reason=messages.recycled_reason("rss")))])
        client.drop()
        notice = messages.Gone(worker=ident, reason=messages.recycled_reason("rss"))
        with caplog.at_level(logging.INFO, logger="trapflow.broker.node"):
            broker._on_order(notice, time.monotonic())
        st = broker.state.pool_stats()["noop"]
        assert (st.processed, st.lost, st.pending, st.in_flight) == (1, 0, 0, 0)
        assert broker.state.rejected == {} and len(broker.results.out) == 1
        assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == []


@pytest.mark.timeout(60)
def test_forged_stopping_notice_is_refused(run_dir: Path, prefix: str) -> None:
    """Only the supervisor may tell the broker a planned stop began (it quiets warnings):
    not a worker, not whoever claims the supervisor's old identity on the workers socket."""
    make_private(run_dir)
    cfg = Config(pools={"noop": PoolConfig(plugin="noop")})
    broker = BrokerNode(NodeSpec("broker", "broker", cfg, run_dir))
    try:
        broker._on_worker_msg(b"noop:0:1", messages.Stopping(), [])
        assert (broker.winding_down, broker.refused) == (False, {"forged_stopping": 1})
        broker._on_worker_msg(b"supervisor", messages.Stopping(), [])
        assert (broker.winding_down, broker.refused) == (False, {"forged_stopping": 2})
        broker._on_order(messages.Stopping(), time.monotonic())
        assert broker.winding_down
    finally:
        broker.close()


@pytest.mark.timeout(120)
def test_a_worker_growing_past_max_rss_mb_is_recycled_without_loss(
        spawn, run_dir: Path) -> None:
    """A plugin keeps 20 MiB per pair: past max_rss_mb its worker answers the pair, says
    goodbye and a new process (new pid) takes over; no pair is lost, the restart budget is
    untouched, and nothing of it is a warning."""
    cfg = write_config(run_dir.parent / "rss.yaml", {"source": SMALL, "pools": only_pools({
        "grow": {"plugin": GROW, "policy": "fifo:8", "max_rss_mb": 160, "params": {"mb": 20}},
    })})
    p: Pipeline = spawn(["--config", str(cfg), "--duration", "6"], run_dir)
    code, out, err = p.wait(100)
    assert code == 0, err
    ledger = _ledger(run_dir)
    pool = ledger["pools"]["grow"]
    assert pool["lost"] == 0 and pool["restarts"] == 0, pool
    assert pool["recycled"].get("rss", 0) >= 1, pool
    sup = ledger["supervision"]
    assert sup["recycled"]["grow"]["rss"] == pool["recycled"]["rss"]
    assert sup["gave_up"] == 0 and sup["capped"] == 0
    assert [e["node"] for e in sup["timeline"] if e["kind"] == "recycled"] == (
        ["worker:grow:0"] * pool["recycled"]["rss"])
    rows = [r["grow"] for r in p.results()]
    assert pool["processed"] == len(rows)
    pids = {r["pid"] for r in rows}
    assert len(pids) >= 2, pids  # the first worker and a successor answered
    # Each worker stopped at its limit: never a pair begun past max_rss_mb.
    assert max(r["rss_mb"] for r in rows) < 160 + 20 + 5, rows
    assert len({r["seq"] for r in rows}) == len(rows)  # the goodbye pair answered once
    assert "recycled" in out  # the totals say so
    assert not _warnings(err), err
    assert not _warnings((run_dir / "trapflow.log").read_text())


@pytest.mark.timeout(120)
@pytest.mark.parametrize("transport", ["shm", "zmq"])
def test_max_jobs_recycles_and_a_normal_run_logs_no_warning(
        spawn, run_dir: Path, transport: str) -> None:
    """max_jobs: every worker of the pool is replaced after that many pairs, the pool goes
    on, nothing is lost, over local links (shm) and over the workers' ROUTER (zmq); a pool
    with max_pending_age_s drops the pairs that waited too long, counted as stale. Also
    pins the broker's "cannot reach worker: Broken pipe" warning at a normal --duration
    stop: a short normal run's console and log have no WARNING."""
    cfg = write_config(run_dir.parent / "jobs.yaml", {
        "source": {**SMALL, "rate_hz": 20.0}, "frames": {"transport": transport},
        "pools": only_pools({
            "noop": {"plugin": "noop", "count": 2, "policy": "fifo:8", "max_jobs": 4},
            "slow": {"plugin": "slow", "count": 2, "policy": "latest",
                     "params": {"delay_s": 0.05}},
            # Pairs wait longer than 0.5 s for its one worker: dropped as stale.
            "aged": {"plugin": "slow", "policy": "fifo:32", "max_pending_age_s": 0.5,
                     "params": {"delay_s": 0.3}},
        })})
    p: Pipeline = spawn(["--config", str(cfg), "--duration", "4"], run_dir)
    code, out, err = p.wait(100)
    assert code == 0, err
    ledger = _ledger(run_dir)
    noop, slow = ledger["pools"]["noop"], ledger["pools"]["slow"]
    assert noop["recycled"].get("jobs", 0) >= 2 and noop["restarts"] == 0, noop
    assert noop["lost"] == 0 and slow["lost"] == 0, ledger["pools"]
    assert noop["processed"] >= 8 and slow["processed"] > 0, ledger["pools"]
    assert slow["recycled"] == {}
    aged = ledger["pools"]["aged"]
    assert aged["dropped_stale"] > 0 and aged["lost"] == 0, aged
    for name, pool in ledger["pools"].items():  # every pair in exactly one state
        states = (pool["processed"] + pool["dropped_by_policy"] + pool["dropped_stale"]
                  + pool["timed_out"] + pool["failed"] + pool["lost"]
                  + pool.get("unfinished_at_stop", 0))
        assert states == ledger["produced"], (name, pool, ledger["produced"])
    assert "recycled" in out  # the totals say so
    assert not _warnings(err), err
    assert not _warnings((run_dir / "trapflow.log").read_text())

