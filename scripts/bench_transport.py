"""Transport benchmark: trapflow's broker path against raw pyzmq PUSH/PULL, in one run.

1280x720 stereo pairs, JPEG (q90) and raw, between separate processes on one host.
Throughput is lossless with back-pressure (a window of pairs in flight per consumer);
latency is one-way at a fixed 30 pairs/s (stamp before send -> consumer holds the
buffer); CPU and peak RSS are read from /proc. Prints JSON on stdout.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import msgspec
import numpy as np
import psutil
import zmq

from trapflow import config as configmod
from trapflow import messages
from trapflow.node import NodeSpec, node_main
from trapflow.transport import Endpoints

PAGE = 4096
WINDOW = 4  # pairs in flight per consumer, as in the peer measurements


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


def cpu_s(pid: int) -> float:
    try:
        t = psutil.Process(pid).cpu_times()
        return float(t.user + t.system)
    except psutil.NoSuchProcess:
        return 0.0


# --- raw pyzmq baseline ------------------------------------------------------------------


def _raw_consumer(endpoint: str, conn: Any) -> None:
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
        h = msgspec.msgpack.decode(frames[0].bytes)
        for f in frames[1:]:
            np.frombuffer(f.buffer, np.uint8)[::PAGE].sum()
        lats.append(t - h["t_mono_ns"])
        n += 1
    conn.send({"n": n, "lat": lats, "rss": peak_rss_mb(os.getpid())})
    ctx.destroy(linger=0)


def raw_pyzmq(kind: str, seconds: float, rate: float | None, tmp: Path) -> dict[str, Any]:
    left, right = make_payload(kind)
    endpoint = f"ipc://{tmp}/raw-{kind}-{rate}.sock"
    ctx = zmq.Context()
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.SNDHWM, WINDOW // 2)
    push.bind(endpoint)
    here, there = mp.Pipe()
    proc = mp.get_context("spawn").Process(target=_raw_consumer, args=(endpoint, there))
    proc.start()
    here.recv()
    time.sleep(0.3)
    c0 = cpu_s(os.getpid()) + cpu_s(proc.pid)
    n, t0 = 0, time.monotonic()
    period = 1.0 / rate if rate else 0.0
    while (now := time.monotonic()) - t0 < seconds:
        if rate:
            wait = t0 + n * period - now
            if wait > 0:
                time.sleep(wait)
        push.send_multipart([header(n, kind), left, right], copy=False)
        n += 1
    push.send(b"end")
    res = here.recv()
    dt = time.monotonic() - t0
    cpu = cpu_s(os.getpid()) + cpu_s(proc.pid) - c0
    proc.join(5)
    ctx.destroy(linger=0)
    return {"pairs": res["n"], "pairs_s": res["n"] / dt, "lat_us": _pcts(res["lat"]),
            "cpu_us_per_pair": cpu / max(res["n"], 1) * 1e6,
            "rss_mb": {"source": peak_rss_mb(os.getpid()), "consumer": res["rss"]}}


def _pcts(lat_ns: list[int]) -> dict[str, float]:
    if not lat_ns:
        return {}
    xs = sorted(lat_ns[len(lat_ns) // 10:])  # skip warm-up
    q = statistics.quantiles(xs, n=100) if len(xs) > 2 else xs * 99
    return {"p50": q[49] / 1e3, "p99": q[98] / 1e3, "max": xs[-1] / 1e3}


# --- trapflow: the real broker and worker processes ---------------------------------------


def trapflow_path(kind: str, seconds: float, rate: float | None, workers: int,
                  tmp: Path, pools: int = 1) -> dict[str, Any]:
    """Pairs into the real broker, no-op workers, results counted back (window per worker)."""
    run_dir = Path(tempfile.mkdtemp(prefix="tfb-", dir=tmp))
    cfg = configmod.from_data({
        "source": {"encoding": "raw" if kind == "raw" else "jpeg"},
        "pools": {f"p{i}": {"plugin": "noop", "count": workers, "policy": "fifo:64",
                            "credit": 2} for i in range(pools)},
        "log_level": "WARNING",
    })
    ep = Endpoints.for_run(cfg.network, run_dir)
    ctx = zmq.Context()
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.SNDHWM, 64)
    push.connect(ep.capture)
    results = ctx.socket(zmq.PULL)
    results.connect(ep.results)
    hb = ctx.socket(zmq.PULL)  # stand-in supervisor: heartbeats are received and ignored
    hb.bind(ep.heartbeat)
    q = mp.get_context("spawn").Queue()
    specs = [NodeSpec("broker", "broker", cfg, run_dir)] + [
        NodeSpec("worker", f"worker:p{p}:{i}", cfg, run_dir, pool=f"p{p}", index=i)
        for p in range(pools) for i in range(workers)]
    procs = [mp.get_context("spawn").Process(target=node_main, args=(s, q, os.getpid()))
             for s in specs]
    for p in procs:
        p.start()
    left, right = make_payload(kind)
    # Warm up until every worker answered (their READY reached the broker).
    seq = 0
    done = 0
    deadline = time.monotonic() + 30
    while done < 3 * workers * pools and time.monotonic() < deadline:
        push.send_multipart([header(seq, kind), left, right], copy=False)
        seq += 1
        if results.poll(100):
            while results.poll(0):
                results.recv()
                done += 1
    time.sleep(0.5)
    while results.poll(200):
        results.recv()
    pids = [os.getpid()] + [p.pid for p in procs]
    c0 = [cpu_s(p) for p in pids]
    lats: list[int] = []
    window = WINDOW * workers
    sent = completed = 0
    expected = pools  # each pair yields one result per pool
    t0 = time.monotonic()
    period = 1.0 / rate if rate else 0.0
    while (now := time.monotonic()) - t0 < seconds:
        if rate:
            wait = t0 + sent * period - now
            if wait > 0 and results.poll(int(wait * 1000) + 1) == 0:
                continue
        elif sent - completed // expected >= window:
            results.poll(1000)
        while results.poll(0):
            r = messages.decode_result(results.recv(copy=False))
            completed += 1
            if isinstance(r.body, messages.Extra):
                lats.append(int(r.body.fields["lat_ns"]))
        if rate and time.monotonic() < t0 + sent * period:
            continue
        if not rate and sent - completed // expected >= window:
            continue
        push.send_multipart([header(seq, kind), left, right], copy=False)
        seq += 1
        sent += 1
    end = time.monotonic() + 5
    while completed < sent * expected and time.monotonic() < end:
        if results.poll(200):
            r = messages.decode_result(results.recv(copy=False))
            completed += 1
            if isinstance(r.body, messages.Extra):
                lats.append(int(r.body.fields["lat_ns"]))
    dt = time.monotonic() - t0
    cpu = [cpu_s(p) - c for p, c in zip(pids, c0, strict=False)]
    rss = {"harness": peak_rss_mb(os.getpid()), "broker": peak_rss_mb(procs[0].pid)}
    for i, p in enumerate(procs[1:]):
        rss[f"worker{i}"] = peak_rss_mb(p.pid)
    for p in procs:
        p.terminate()
    for p in procs:
        p.join(5)
    ctx.destroy(linger=0)
    per_pool = completed / expected
    return {"pairs": int(per_pool), "pairs_s": per_pool / dt, "lost": sent - int(per_pool),
            "lat_us": _pcts(lats),
            "cpu_us_per_pair": sum(cpu) / max(per_pool, 1) * 1e6,
            "cpu_us_per_pair_by_process": dict(zip(
                ["harness", "broker"] + [f"worker{i}" for i in range(len(procs) - 1)],
                [round(c / max(per_pool, 1) * 1e6, 1) for c in cpu], strict=True)),
            "broker_cpu_pct": cpu[1] / dt * 100, "rss_mb": rss}


def markdown(out: dict[str, Any]) -> str:
    """The transport results as markdown tables, ratios against raw pyzmq in the same run."""
    lines = ["## Transport: trapflow broker path vs raw pyzmq PUSH/PULL (same run)", "",
             f"Machine: {out['machine']}", "",
             "| payload | pyzmq pairs/s | trapflow pairs/s | ratio | lost | CPU us/pair "
             "pyzmq / trapflow | trapflow CPU us/pair by process |",
             "|---|---:|---:|---:|---:|---:|---|"]
    for kind in ("jpeg", "raw"):
        t = out[kind]["throughput"]
        b, f = t["pyzmq_push_pull"], t["trapflow"]
        lines.append(f"| {kind} 1280x720 pair | {b['pairs_s']:,.0f} | {f['pairs_s']:,.0f} | "
                     f"{t['ratio']:.2f}x | {f['lost']} | {b['cpu_us_per_pair']:,.0f} / "
                     f"{f['cpu_us_per_pair']:,.0f} | {f['cpu_us_per_pair_by_process']} |")
    fan = out["raw"]["fanout3"]
    lines += ["", f"Fan-out 1 -> 3 pools (raw): {fan['pairs_s']:,.0f} pairs/s per pool "
              f"({fan['pairs_s'] / out['raw']['throughput']['pyzmq_push_pull']['pairs_s']:.2f}x "
              "raw pyzmq 1 -> 1)", "",
              "| 30 pairs/s | pyzmq p50 / p99 us | trapflow p50 / p99 us | ratio p50 | "
              "broker CPU % of a core | peak RSS MB (trapflow) |",
              "|---|---:|---:|---:|---:|---|"]
    for kind in ("jpeg", "raw"):
        lat = out[kind]["latency_30hz"]
        b, f = lat["pyzmq_push_pull"], lat["trapflow"]
        rss = ", ".join(f"{k} {v:.0f}" for k, v in f["rss_mb"].items())
        lines.append(f"| {kind} | {b['lat_us']['p50']:,.0f} / {b['lat_us']['p99']:,.0f} | "
                     f"{f['lat_us']['p50']:,.0f} / {f['lat_us']['p99']:,.0f} | "
                     f"{lat['ratio_p50']:.2f}x | {f['broker_cpu_pct']:.1f} | {rss} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--latency-seconds", type=float, default=8.0)
    ap.add_argument("--out", type=Path, default=Path("bench-results"))
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="tfbench-"))
    out: dict[str, Any] = {"machine": {"cores": os.cpu_count(), "python": sys.version.split()[0],
                                       "pyzmq": zmq.__version__, "libzmq": zmq.zmq_version()}}
    for kind in ("jpeg", "raw"):
        print(f"[bench] {kind}: raw pyzmq throughput", file=sys.stderr)
        base = raw_pyzmq(kind, args.seconds, None, tmp)
        print(f"[bench] {kind}: trapflow throughput", file=sys.stderr)
        tf = trapflow_path(kind, args.seconds, None, 1, tmp)
        print(f"[bench] {kind}: 30 Hz latency", file=sys.stderr)
        base30 = raw_pyzmq(kind, args.latency_seconds, 30.0, tmp)
        tf30 = trapflow_path(kind, args.latency_seconds, 30.0, 1, tmp)
        out[kind] = {
            "throughput": {"pyzmq_push_pull": base, "trapflow": tf,
                           "ratio": tf["pairs_s"] / base["pairs_s"]},
            "latency_30hz": {"pyzmq_push_pull": base30, "trapflow": tf30,
                             "ratio_p50": tf30["lat_us"]["p50"] / base30["lat_us"]["p50"]},
        }
    print("[bench] raw: fan-out to 3 pools", file=sys.stderr)
    out["raw"]["fanout3"] = trapflow_path("raw", args.seconds, None, 1, tmp, pools=3)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "transport.json").write_text(json.dumps(out, indent=1))
    (args.out / "transport.md").write_text(markdown(out))
    print(markdown(out))


if __name__ == "__main__":
    main()
