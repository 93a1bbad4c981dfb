"""Shared-memory frame ring benchmark: pairs written once into the ring with only a FrameRef
over a local link (as trapflow sends descriptors), against raw pyzmq PUSH/PULL carrying the
bytes, in one run.

1280x720 stereo pairs, JPEG (q90, ~252 KB a pair) and raw (5.5 MB a pair), 1 producer ->
1 consumer process; the consumer touches every page of both images. Throughput is lossless
with back-pressure (4 pairs in flight: a ring of 4 slots, freed by the consumer); latency
is one-way at a fixed 30 pairs/s (stamp before the write into the ring -> consumer holds
usable views). Writes shm.json and shm.md into --out and prints the table.

Usage: python -m benchmarks.shm [--quick] [--out bench-results] [--seconds 4]
       [--latency-seconds 6]
"""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import msgspec
import zmq

from benchmarks import harness as h
from benchmarks.transport import (
    PAGE,
    WINDOW,
    _pcts,
    header,
    make_payload,
    peak_rss_mb,
    raw_pyzmq,
)
from trapflow.wire import frame_msgs, frame_ring, messages
from trapflow.wire.links import accept_link, connect_link, listen_link


def _shm_consumer(name: str, path: str, conn: Any) -> None:
    link = connect_link(path)
    ring = frame_ring.FrameRing(name)  # the lifetime owner here: frees after use
    reader = frame_ring.RingReader(name)
    lats: list[int] = []
    n = stale = 0
    left = right = None
    conn.send("ready")
    while True:
        frames = link.recv() if link.wait(1000) else None
        if frames is None:
            continue
        if len(frames) == 1:
            break
        ref = frame_msgs.decode_frame_ref(frames[1])
        try:
            left, right = reader.view(ref)
            t = time.monotonic_ns()
            meta = msgspec.msgpack.decode(frames[0])
            left[::PAGE].sum()
            right[::PAGE].sum()
            reader.check(ref)
            lats.append(t - meta["t_mono_ns"])
            n += 1
        except frame_ring.StaleFrame:
            stale += 1
        ring.free_ref(ref)
        link.send([b"free"])
    del left, right
    conn.send({"n": n, "stale": stale, "lat": lats, "rss": peak_rss_mb(os.getpid())})
    reader.close()
    ring.close()
    link.close()


def shm_ring(kind: str, seconds: float, rate: float | None, tmp: Path) -> dict[str, Any]:
    left, right = make_payload(kind)
    listener = listen_link(f"{tmp}/shm-{kind}-{rate}.link")
    ring = frame_ring.FrameRing.create(WINDOW, frame_ring.slot_capacity(1280, 720))
    writer = frame_ring.RingWriter(ring.name)
    here, there = mp.Pipe()
    proc = mp.get_context("spawn").Process(
        target=_shm_consumer, args=(ring.name, listener.getsockname(), there))
    proc.start()
    try:
        while (link := accept_link(listener)) is None:
            time.sleep(0.01)
        here.recv()
        time.sleep(0.3)
        c0 = h.tree_cpu(os.getpid())  # this process and its consumer
        n, full, t0 = 0, 0, time.monotonic()
        while time.monotonic() - t0 < seconds:
            h.pace(t0, n, rate)
            while link.recv() is not None:  # the consumer's frees
                pass
            hdr = header(n, kind)  # stamped before the write: the ring is the transport
            slot = writer.acquire()
            if slot is None:  # 4 pairs in flight: wait for the consumer to free one
                full += 1
                link.wait(1000)
                continue
            ref = writer.write(slot, left, right)
            link.send([hdr, messages.encode(ref)])
            n += 1
        link.send([b"end"])
        res = here.recv()
        dt = time.monotonic() - t0
        cpu = h.tree_cpu(os.getpid()) - c0
        proc.join(5)
    finally:
        if proc.is_alive():
            proc.kill()
            proc.join(5)
        if link is not None:
            link.close()
        listener.close()
        writer.close()
        ring.close()
    return {"pairs": res["n"], "pairs_s": res["n"] / dt, "stale": res["stale"],
            "lost": n - res["n"] - res["stale"], "ring_full_waits": full,
            "lat_us": _pcts(res["lat"]), "cpu_us_per_pair": cpu / max(res["n"], 1) * 1e6,
            "rss_mb": {"source": peak_rss_mb(os.getpid()), "consumer": res["rss"]}}


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="1.5 s windows")
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--latency-seconds", type=float, default=6.0)
    args = ap.parse_args()
    if args.quick:
        args.seconds, args.latency_seconds = 1.5, 3.0
    frame_ring.cleanup_stale()
    tmp = Path(tempfile.mkdtemp(prefix="tfshm-"))
    out: dict[str, Any] = {"machine": {"cores": os.cpu_count(), "python": sys.version.split()[0],
                                       "pyzmq": zmq.__version__, "libzmq": zmq.zmq_version()}}
    for kind in ("jpeg", "raw"):
        h.log("shm", f"{kind}: throughput")
        base = raw_pyzmq(kind, args.seconds, None, tmp)
        shm = shm_ring(kind, args.seconds, None, tmp)
        h.log("shm", f"{kind}: 30 Hz latency")
        base30 = raw_pyzmq(kind, args.latency_seconds, 30.0, tmp)
        shm30 = shm_ring(kind, args.latency_seconds, 30.0, tmp)
        out[kind] = {
            "throughput": {"pyzmq_push_pull": base, "shm_ring": shm,
                           "ratio": shm["pairs_s"] / base["pairs_s"]},
            "latency_30hz": {"pyzmq_push_pull": base30, "shm_ring": shm30,
                             "ratio_p50": shm30["lat_us"]["p50"] / base30["lat_us"]["p50"]},
        }
    tables = [result(out)]
    h.write(args.out, "shm", tables)
    print(h.markdown(tables))


def result(out: dict[str, Any]) -> h.Result:
    """The ring alone (no broker): a floor for what the brokered shm path can reach."""
    r = h.Result("shm", "The shared-memory ring alone, 1 producer -> 1 consumer (no broker), "
                 "descriptors over a local link", key="payload", data=out)
    for kind in ("jpeg", "raw"):
        t, lat = out[kind]["throughput"], out[kind]["latency_30hz"]
        b, ring = lat["pyzmq_push_pull"]["lat_us"], lat["shm_ring"]["lat_us"]
        r.add(kind, **{
            "pyzmq pairs/s": h.Figure(round(t["pyzmq_push_pull"]["pairs_s"], 1), digits=0),
            "ring pairs/s": h.Figure(round(t["shm_ring"]["pairs_s"], 1), digits=0),
            "x pyzmq": h.Figure(round(t["ratio"], 3)),
            "pyzmq p50 at 30 Hz": h.Figure(round(b["p50"], 1), "us", digits=0),
            "pyzmq p99 at 30 Hz": h.Figure(round(b["p99"], 1), "us", digits=0),
            "ring p50 at 30 Hz": h.Figure(round(ring["p50"], 1), "us", digits=0),
            "ring p99 at 30 Hz": h.Figure(round(ring["p99"], 1), "us", digits=0)})
    return r


if __name__ == "__main__":
    main()
