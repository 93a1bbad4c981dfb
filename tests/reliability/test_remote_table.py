"""Hundreds of hellos from an authorised remote key: the broker's table of remote workers
stays bounded, forgets the silent ones, and the broker's memory comes back.

Pins issue 26 item 10: 300 hellos from an authorised key grew the broker by 11.7 MB and
every entry was kept. Real CURVE handshakes with a key in authorized_keys, against a real
pipeline; each hello from its own socket, named as the protocol asks (POOL@HOST:INDEX:PID).
"""

from __future__ import annotations

import functools
import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil
import pytest
import zmq

from tests.conftest import Pipeline, poll_for
from tests.integration.test_remote_workers import SMALL, free_port, keys, remote_config
from tests.reliability import figures
from trapflow.broker.remote_state import MAX_REMOTE_WORKERS
from trapflow.wire import messages
from trapflow.wire.curve import client_keys
from trapflow.wire.transport import CurveKeys

pytestmark = pytest.mark.slow  # starts whole pipelines

__all__ = ["keys"]  # the key fixture, used by name
HELLOS = 300
# 300 connections' CURVE sessions and buffers are libzmq's, freed when they close; the broker
# gives the pages back (release_memory) once it forgot their entries. A second round may add
# little: no growth without bound.
SECOND_ROUND_BYTES = 3 << 20
MAX_GROWTH_BYTES = 10 << 20


def _broker(p: Pipeline) -> dict[str, Any]:
    st = p.status()
    return next(n for n in st["nodes"] if n["name"] == "broker") if st else {}


def _forgotten(p: Pipeline, at_least: int) -> dict[str, int] | None:
    """The broker's counters once it forgot at_least silent remote workers, else None."""
    c: dict[str, int] = _broker(p).get("counters", {})
    return c if c.get("remote_forgotten", 0) >= at_least else None


def _hellos(p: Pipeline, ck: CurveKeys, bind: str, zctx: zmq.Context[zmq.Socket[bytes]],
            rnd: int) -> None:
    """HELLOS hellos, each from its own socket: the first MAX_REMOTE_WORKERS welcomed, the
    rest refused as the table is full; the sockets closed again."""
    socks: list[zmq.Socket[bytes]] = []
    try:
        for i in range(HELLOS):
            name = f"far@evil{rnd}:{i}:1"
            s = zctx.socket(zmq.DEALER)
            socks.append(s)
            s.setsockopt(zmq.IDENTITY, name.encode())
            s.curve_publickey, s.curve_secretkey, s.curve_serverkey = (
                ck.public, ck.secret, ck.server)
            s.connect(bind)
            s.send(messages.encode(messages.Hello(worker=name, pool="far", host="evil",
                                                  owner="evil-sup")))
        welcomed = refused = 0
        deadline = time.monotonic() + 30
        while welcomed + refused < HELLOS and time.monotonic() < deadline:
            for s in socks:
                while s.poll(0):
                    w = messages.decode_welcome(s.recv())
                    welcomed += not w.error
                    refused += bool(w.error)
            time.sleep(0.05)
        assert (welcomed, refused) == (MAX_REMOTE_WORKERS, HELLOS - MAX_REMOTE_WORKERS)
        st = p.status()
        assert st is not None and len(st["stats"].get("remote", [])) <= MAX_REMOTE_WORKERS
    finally:
        for s in socks:
            s.close(linger=0)


@pytest.mark.timeout(200)
def test_300_hellos_from_an_authorised_key_keep_the_remote_table_bounded(
        spawn: Callable[..., Pipeline], run_dir: Path, keys: dict[str, Path],
        zctx: zmq.Context[zmq.Socket[bytes]]) -> None:
    bind = f"tcp://127.0.0.1:{free_port()}"
    cfg = remote_config(run_dir.parent / "hellos.yaml", bind, keys, {
        "far": {"plugin": "digest", "policy": "latest", "count": 0, "remote": True},
    }, {**SMALL, "rate_hz": 5.0})
    p: Pipeline = spawn(["--config", str(cfg)], run_dir)
    pid = next(n for n in p.wait_active()["nodes"] if n["name"] == "broker")["pid"]
    before = psutil.Process(pid).memory_info().rss
    ck = client_keys(keys["worker"])
    after = []
    for rnd in (1, 2):
        _hellos(p, ck, bind, zctx, rnd)
        # Silent, never ready: forgotten after liveness_s, the table empty again, counted.
        c = poll_for(functools.partial(_forgotten, p, rnd * MAX_REMOTE_WORKERS), 30,
                     what="the silent ones forgotten")
        st = poll_for(lambda: (s := p.status()) and not s["stats"].get("remote") and s, 10,
                      what="an empty remote table")
        time.sleep(2.0)
        after.append(psutil.Process(pid).memory_info().rss - before)
    print(f"broker RSS growth after each round of {HELLOS} hellos, once the senders left: "
          f"{[round(g / 2**20, 2) for g in after]} MiB; counters {c}")
    figures("remote_hellos", hellos=2 * HELLOS, refused=c["refused_remote_table_full"],
            forgotten=c["remote_forgotten"], growth_mb={"broker": round(max(after) / 2**20, 2)})
    assert c["refused_remote_table_full"] == 2 * (HELLOS - MAX_REMOTE_WORKERS), c
    # Given back once the senders left (the issue: +11.7 MB, all kept), and what the first
    # round took is reused by the second: no growth without bound.
    assert max(after) < MAX_GROWTH_BYTES, after
    assert after[1] - after[0] < SECOND_ROUND_BYTES, after
    assert st["stats"]["pools"]["far"]["workers"] == 0
    code, _, err = p.stop(signal.SIGINT, timeout=20)
    assert code == 0, err
