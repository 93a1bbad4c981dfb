"""Transport benchmark: trapflow's broker path against raw pyzmq PUSH/PULL, in one run.

1280x720 stereo pairs, JPEG (q90) and raw, between separate processes on one host.
Throughput is lossless with back-pressure (a window of pairs in flight per consumer);
latency is one-way at a fixed 30 pairs/s (stamp before send -> consumer holds the
buffer); CPU and peak RSS are read from /proc. Writes transport.json and transport.md into
--out and prints the tables.

Usage: python -m benchmarks.transport [--quick] [--repeats 5] [--out bench-results]
       [--seconds 4] [--latency-seconds 8]
"""

from __future__ import annotations

import gc
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

import cv2
import msgspec
import numpy as np
import zmq

from benchmarks import harness as h
from benchmarks import transport_report as report
from trapflow.config import schema as configmod
from trapflow.runtime.node import NodeSpec, node_main
from trapflow.wire import messages
from trapflow.wire.endpoints import Endpoints
from trapflow.wire.frame_ring import FrameRing, RingWriter, ring_slots, slot_capacity
from trapflow.wire.links import Link, LinkClosed, connect_link

PAGE = 4096
WINDOW = 4  # pairs in flight per consumer, as in the peer measurements
# trapflow's frame paths: bytes through the broker; the ring, written by a capture that
# copies a pair it holds (as a camera or a decoder with its own buffers makes it); the ring
# with the pair made in place in the slot (begin/commit, the harness touches one byte a
# page as the consumer does): no copy on either side, the ring's own cost.
FRAMES = ("zmq", "shm", "shm_inplace")


def make_payload(kind: str) -> tuple[bytes, bytes]:
    """A realistic pair: textured 1280x720 images (noise compresses like a real scene)."""
    rng = np.random.default_rng(1)
    base = cv2.GaussianBlur(rng.integers(0, 255, (720, 1280, 3), dtype=np.uint8), (0, 0), 1.2)
    left, right = base, np.roll(base, 40, axis=1)
    if kind == "raw":
        return left.tobytes(), right.tobytes()
    q = [cv2.IMWRITE_JPEG_QUALITY, 90]
    return cv2.imencode(".jpg", left, q)[1].tobytes(), cv2.imencode(".jpg", right, q)[1].tobytes()


def header(seq: int, kind: str) -> bytes:
    now = time.monotonic_ns()
    return messages.encode(messages.StereoPair(
        seq=seq, t_wall_ns=time.time_ns(), t_mono_ns=now, t_left_ns=now, t_right_ns=now,
        skew_ns=0, encoding="raw" if kind == "raw" else "jpeg", width=1280, height=720))


def peak_rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


# --- raw pyzmq baseline ------------------------------------------------------------------


def _raw_consumer(endpoint: str, conn: Any) -> None:
    gc.freeze()  # as trapflow's nodes do after start-up: same collector work on both sides
    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.setsockopt(zmq.RCVHWM, WINDOW // 2)
    pull.connect(endpoint)
    lats: list[int] = []
    n = 0
    conn.send("ready")
    while True:
        frames = pull.recv_multipart(copy=False)
        if len(frames) == 1:
            break
        t = time.monotonic_ns()
        meta = msgspec.msgpack.decode(frames[0].bytes)
        for f in frames[1:]:
            np.frombuffer(f.buffer, np.uint8)[::PAGE].sum()
        lats.append(t - meta["t_mono_ns"])
        n += 1
    conn.send({"n": n, "lat": lats, "rss": peak_rss_mb(os.getpid())})
    ctx.destroy(linger=0)


def _raw_link(ctx: zmq.Context[Any], endpoint: str
              ) -> tuple[zmq.Socket[Any], Connection, BaseProcess]:
    """A PUSH bound at endpoint and its raw consumer process, started (it says when it is
    ready, then its counts, over the pipe returned)."""
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.SNDHWM, WINDOW // 2)
    push.bind(endpoint)
    here, there = mp.Pipe()
    proc = mp.get_context("spawn").Process(target=_raw_consumer, args=(endpoint, there))
    proc.start()
    return push, here, proc


def raw_pyzmq(kind: str, seconds: float, rate: float | None, tmp: Path) -> dict[str, Any]:
    left, right = make_payload(kind)
    ctx = zmq.Context()
    push, here, proc = _raw_link(ctx, f"ipc://{tmp}/raw-{kind}-{rate}.sock")
    here.recv()
    time.sleep(0.3)
    c0 = h.tree_cpu(os.getpid())  # this process and its consumer
    n, t0 = 0, time.monotonic()
    while time.monotonic() - t0 < seconds:
        h.pace(t0, n, rate)
        push.send_multipart([header(n, kind), left, right], copy=False)
        n += 1
    push.send(b"end")
    res = here.recv()
    dt = time.monotonic() - t0
    cpu = h.tree_cpu(os.getpid()) - c0
    proc.join(5)
    ctx.destroy(linger=0)
    return {"pairs": res["n"], "pairs_s": res["n"] / dt, "lat_us": _pcts(res["lat"]),
            "cpu_us_per_pair": cpu / max(res["n"], 1) * 1e6,
            "rss_mb": {"source": peak_rss_mb(os.getpid()), "consumer": res["rss"]}}


def raw_pyzmq_fanout(seconds: float, tmp: Path, consumers: int = 3) -> dict[str, Any]:
    """Raw pairs from one source to 3 consumers, each getting every pair (one PUSH each)."""
    left, right = make_payload("raw")
    ctx = zmq.Context()
    pushes, procs, pipes = [], [], []
    for i in range(consumers):
        push, here, proc = _raw_link(ctx, f"ipc://{tmp}/fan-{i}.sock")
        pushes.append(push)
        procs.append(proc)
        pipes.append(here)
    for here in pipes:
        here.recv()
    time.sleep(0.3)
    n, t0 = 0, time.monotonic()
    while time.monotonic() - t0 < seconds:
        hdr = header(n, "raw")
        for push in pushes:
            push.send_multipart([hdr, left, right], copy=False)
        n += 1
    for push in pushes:
        push.send(b"end")
    counts = [here.recv()["n"] for here in pipes]
    dt = time.monotonic() - t0
    for proc in procs:
        proc.join(5)
    ctx.destroy(linger=0)
    return {"pairs_s": min(counts) / dt, "per_consumer": [c / dt for c in counts]}


def _pcts(lat_ns: list[int]) -> dict[str, float]:
    if not lat_ns:
        return {}
    xs = sorted(lat_ns[len(lat_ns) // 10:])  # skip warm-up
    q = statistics.quantiles(xs, n=100) if len(xs) > 2 else xs * 99
    return {"p50": q[49] / 1e3, "p99": q[98] / 1e3, "max": xs[-1] / 1e3}


# --- trapflow: the real broker and worker processes ---------------------------------------


def trapflow_path(kind: str, seconds: float, rate: float | None, workers: int,
                  tmp: Path, pools: int = 1, frames: str = "zmq") -> dict[str, Any]:
    """Pairs into the real broker, no-op workers, results counted back (window per worker).

    The harness plays capture: with frames="shm" it writes each pair once into the ring
    and sends the descriptor over the broker's local link, as capture does; with
    "shm_inplace" it makes the pair in the slot instead (touching a byte a page, no copy);
    with "zmq" it sends the bytes.
    """
    inplace = frames == "shm_inplace"
    frames = "shm" if inplace else frames
    run_dir = Path(tempfile.mkdtemp(prefix="tfb-", dir=tmp))
    cfg = configmod.from_data({
        "source": {"encoding": "raw" if kind == "raw" else "jpeg"},
        "pools": {f"p{i}": {"plugin": "noop", "count": workers, "policy": "fifo:8",
                            "credit": 2} for i in range(pools)}
                  # a pools: section merges over the defaults: switch the default pools off
                  | {name: {"count": 0} for name in configmod.Config().pools},
        "frames": {"transport": frames},
        "log_level": "WARNING",
    })
    ring = writer = None
    ring_name = ""
    if frames == "shm":
        ring = FrameRing.create(ring_slots(cfg.pools.values(), 0, cfg.frames.spare_slots),
                                slot_capacity(1280, 720))
        writer = RingWriter(ring.name)
        ring_name = ring.name
    ep = Endpoints.for_run(cfg.network, run_dir)
    ctx = zmq.Context()
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.SNDHWM, 64)
    push.connect(ep.capture)
    hb = ctx.socket(zmq.PULL)  # stand-in supervisor: heartbeats are received and ignored
    hb.bind(ep.heartbeat)
    specs = [NodeSpec("broker", "broker", cfg, run_dir, ring=ring_name)] + [
        NodeSpec("worker", f"worker:p{p}:{i}", cfg, run_dir, pool=f"p{p}", index=i,
                 ring=ring_name)
        for p in range(pools) for i in range(workers)]
    procs = [mp.get_context("spawn").Process(target=node_main, args=(s, os.getpid()))
             for s in specs]
    for p in procs:
        p.start()
    left, right = make_payload(kind)
    link: Link | None = None
    if kind == "raw":  # capture writes arrays; the ring copies them once
        left_a = np.frombuffer(left, np.uint8)
        right_a = np.frombuffer(right, np.uint8)

    def send(seq: int) -> bool:
        if writer is None:
            push.send_multipart([header(seq, kind), left, right], copy=False)
            return True
        slot = writer.acquire()
        if slot is None:
            return False  # every slot held: the window will free one
        if inplace:
            lv, rv = writer.begin(slot, len(left), len(right))
            lv[::PAGE] = seq & 0xFF  # one store a page, as the consumer loads one
            rv[::PAGE] = seq & 0xFF
            ref = writer.commit(slot)
        else:
            ref = writer.write(slot, left_a if kind == "raw" else left,
                               right_a if kind == "raw" else right)
        nonlocal link
        while link is None:  # as capture does: descriptors over the broker's local link
            try:
                link = connect_link(ep.capture_link)
            except LinkClosed:
                time.sleep(0.05)
        if not link.send([header(seq, kind), messages.encode(ref)]):
            writer.release(slot)
            return False
        return True

    out: Link | None = None
    lats: list[int] = []
    completed = 0

    def take(timeout_ms: int) -> None:
        nonlocal completed, out
        while out is None:  # as the normalizer does: results over the broker's local link
            try:
                out = connect_link(ep.results_link)
            except LinkClosed:
                time.sleep(0.05)
        if not out.wait(timeout_ms):
            return
        got = 0
        while (batch := out.recv()) is not None:  # the broker batches results
            got += len(batch)
            for frame in batch:
                r = messages.decode_result(frame)
                completed += 1
                if isinstance(r.body, messages.Extra):
                    lats.append(int(r.body.fields["lat_ns"]))
        if got:  # acknowledged once per pass, as the normalizer does once they are written
            out.send([messages.encode(messages.ResultsAck(count=got))])

    # Warm up until every worker answered (their READY reached the broker).
    seq = 0
    deadline = time.monotonic() + 30
    while completed < 3 * workers * pools and time.monotonic() < deadline:
        if send(seq):
            seq += 1
        take(100)
    time.sleep(0.5)
    take(200)
    pids = [os.getpid()] + [_pid(p) for p in procs]
    c0 = [h.tree_cpu(p, children=False) for p in pids]  # a row per process
    lats.clear()
    completed = 0
    window = WINDOW * workers
    sent = 0
    t0 = time.monotonic()
    period = 1.0 / rate if rate else 0.0
    while time.monotonic() - t0 < seconds:
        if rate:
            wait = t0 + sent * period - time.monotonic()
            if wait > 0:
                take(int(wait * 1000) + 1)
                continue
        elif sent - completed // pools >= window:
            take(1000)  # results are read when the window is full, as a PUSH blocks at its HWM
            continue
        if send(seq):
            seq += 1
            sent += 1
        else:
            take(10)
    end = time.monotonic() + 5
    while completed < sent * pools and time.monotonic() < end:
        take(200)
    dt = time.monotonic() - t0
    cpu = [h.tree_cpu(p, children=False) - c for p, c in zip(pids, c0, strict=True)]
    rss = {"harness": peak_rss_mb(os.getpid()), "broker": peak_rss_mb(pids[1])}
    for i, pid in enumerate(pids[2:]):
        rss[f"worker{i}"] = peak_rss_mb(pid)
    for p in procs:
        p.terminate()
    for p in procs:
        p.join(5)
    ctx.destroy(linger=0)
    if writer is not None and ring is not None:
        writer.close()
        ring.close()
    per_pool = completed / pools
    names = ["harness", "broker"] + [f"worker{i}" for i in range(len(procs) - 1)]
    return {"frames": "shm_inplace" if inplace else frames, "pairs": int(per_pool),
            "pairs_s": per_pool / dt,
            "lost": sent - int(per_pool), "lat_us": _pcts(lats),
            "cpu_us_per_pair": sum(cpu) / max(per_pool, 1) * 1e6,
            "cpu_us_per_pair_by_process": dict(zip(
                names, [round(c / max(per_pool, 1) * 1e6, 1) for c in cpu], strict=True)),
            "broker_cpu_pct": cpu[1] / dt * 100, "rss_mb": rss}


def _pid(p: mp.process.BaseProcess) -> int:
    assert p.pid is not None, "a started process has a pid"
    return p.pid


def _median_run(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The run with the median pairs/s, with the spread of all runs added."""
    ordered = sorted(runs, key=lambda r: r["pairs_s"])
    mid = dict(ordered[len(ordered) // 2])
    mid["pairs_s_runs"] = [round(r["pairs_s"], 1) for r in runs]
    return mid


def jpeg_decode_cost(n: int = 20) -> dict[str, float]:
    """CPU a worker spends decoding one 1280x720 JPEG pair (what raw frames over shm save)."""
    left, right = make_payload("jpeg")
    bufs = [np.frombuffer(b, np.uint8) for b in (left, right)]
    cv2.setNumThreads(1)
    t0 = time.process_time()
    for _ in range(n):
        for b in bufs:
            cv2.imdecode(b, cv2.IMREAD_COLOR)
    per_pair = (time.process_time() - t0) / n
    return {"decode_ms_per_pair": per_pair * 1e3}


def main() -> None:
    ap = h.options(__doc__, repeats=5, quick_help="1.5 s windows, 2 repeats")
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--latency-seconds", type=float, default=8.0)
    args = ap.parse_args()
    if args.quick:
        args.seconds, args.latency_seconds, args.repeats = 1.5, 3.0, 2
    tmp = Path(tempfile.mkdtemp(prefix="tfbench-"))
    gc.freeze()  # every producer here (pyzmq's and trapflow's) runs with a frozen heap
    out: dict[str, Any] = {"machine": {"cores": os.cpu_count(), "python": sys.version.split()[0],
                                       "pyzmq": zmq.__version__, "libzmq": zmq.zmq_version()},
                           "load": {"before": round(os.getloadavg()[0], 2)},
                           "repeats": args.repeats, "window": WINDOW, "frames": FRAMES}
    for kind in ("jpeg", "raw"):
        out[kind] = measure_kind(kind, args.seconds, args.latency_seconds, args.repeats, tmp)
    h.log("transport", "raw: fan-out to 3 pools")
    base3 = raw_pyzmq_fanout(args.seconds, tmp)
    out["raw"]["fanout3"] = {"pyzmq_push_pull": base3, **{
        f"trapflow_{f}": trapflow_path("raw", args.seconds, None, 1, tmp, pools=3, frames=f)
        for f in FRAMES}}
    out["jpeg_decode"] = jpeg_decode_cost()
    out["load"]["after"] = round(os.getloadavg()[0], 2)
    tables = report.results(out)
    h.write(args.out, "transport", tables)
    print(h.markdown(tables))


def measure_kind(kind: str, seconds: float, latency_seconds: float, repeats: int,
                 tmp: Path) -> dict[str, Any]:
    """Throughput (interleaved repeats, the median run kept) and 30 Hz latency of one
    payload kind on every path."""
    h.log("transport", f"{kind}: throughput (pyzmq, trapflow zmq, trapflow shm)")
    # Interleaved repeats, median kept: a shared machine's noise hits every path alike.
    runs: dict[str, list[dict[str, Any]]] = {"base": [], **{f: [] for f in FRAMES}}
    for _ in range(repeats):
        runs["base"].append(raw_pyzmq(kind, seconds, None, tmp))
        for f in FRAMES:
            runs[f].append(trapflow_path(kind, seconds, None, 1, tmp, frames=f))
    base = _median_run(runs["base"])
    tf = {f: _median_run(runs[f]) for f in FRAMES}
    h.log("transport", f"{kind}: 30 Hz latency")
    base30 = raw_pyzmq(kind, latency_seconds, 30.0, tmp)
    tf30 = {f: trapflow_path(kind, latency_seconds, 30.0, 1, tmp, frames=f) for f in FRAMES}
    return {
        "throughput": {"pyzmq_push_pull": base, **{f"trapflow_{f}": tf[f] for f in FRAMES},
                       **{f"ratio_{f}": tf[f]["pairs_s"] / base["pairs_s"] for f in FRAMES},
                       **{f"paired_{f}": [r["pairs_s"] / b["pairs_s"] for b, r in
                                          zip(runs["base"], runs[f], strict=True)]
                          for f in FRAMES}},
        "latency_30hz": {"pyzmq_push_pull": base30, **{f"trapflow_{f}": tf30[f] for f in FRAMES},
                         **{f"ratio_p50_{f}": tf30[f]["lat_us"]["p50"] / base30["lat_us"]["p50"]
                            for f in FRAMES}},
    }


if __name__ == "__main__":
    main()
