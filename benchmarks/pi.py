"""The deployment table, measured on the device itself (Raspberry Pi 5, Jetson, any board):
what each algorithm costs per pair, what the pipeline adds around them, and the VO floor.

1. Per algorithm: each built-in plugin alone in this process on one core (one OpenCV and
   one onnxruntime thread, as a pool's worker runs it), CPU and wall ms per pair on pairs
   of the moving synthetic world at --size; the detector both as int8 (the default) and
   fp32. pairs/s per core = 1000 / CPU ms.
2. Parallel overhead: the default pipeline (mono + stereo + vo, `trapflow start`) at
   --rate pairs/s: CPU per pair of every process against the part inside the plugins'
   process() (the rest is capture, encoding, decoding, broker, normalizer, supervisor).
3. VO floor: VO pairs/s while the stereo pool burns 2 s and two mono workers 100 ms of CPU
   per pair (recognisers saturating every core), against the capture rate.

Usage: python -m benchmarks.pi [--quick] [--size 1280x720] [--rate 10] [--out bench-results]
(scripts/bench.sh --pi runs it). Writes pi.json and pi.md into --out and prints pi.md.
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from benchmarks import cpu as pipeline_cpu
from benchmarks import harness as h
from benchmarks.algorithms import PLUGINS, _frames
from trapflow.calibration.camera import StereoRig
from trapflow.testing.kit import make_context, make_pair

#: (row name, pool, params): the detector as shipped (int8) and as fp32
ALGORITHMS: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("crab detector, int8 (default)", "mono", {}),
    ("crab detector, fp32", "mono", {"variant": "fp32"}),
    ("scene classifier", "stereo", {}),
    ("stereo VO", "vo", {}),
    ("AprilTags", "tags", {}),
)


def device() -> str:
    """The board's name where the kernel gives one (Pi, Jetson), else the CPU's."""
    for path in ("/proc/device-tree/model", "/sys/firmware/devicetree/base/model"):
        try:
            return Path(path).read_text().strip("\x00\n ")
        except OSError:
            pass
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("model name", "Model")):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def per_algorithm(rig: StereoRig, pairs: int) -> list[dict[str, Any]]:
    """CPU and wall ms per pair of each algorithm alone, one thread, after one warm-up pair."""
    cv2.setNumThreads(1)
    rows = []
    for name, pool, params in ALGORITHMS:
        frames = _frames(pool, rig, pairs + 1)
        worker = PLUGINS[pool]()
        worker.configure(params, make_context(rig, pool=pool))
        worker.process(make_pair(*frames[0], seq=0))
        cpu, wall = [], []
        for i, (left, right) in enumerate(frames[1:], start=1):
            c, t = time.process_time(), time.perf_counter()
            worker.process(make_pair(left, right, seq=i))
            cpu.append(1000 * (time.process_time() - c))
            wall.append(1000 * (time.perf_counter() - t))
        worker.shutdown()
        ms = float(np.median(cpu))
        iqr = h.summarise(cpu, "iqr")
        rows.append({"algorithm": name, "pool": pool, "cpu_ms": round(ms, 2),
                     "cpu_ms_iqr": [round(iqr.low, 2), round(iqr.high, 2)],
                     "wall_ms": round(float(np.median(wall)), 2),
                     "pairs_per_s_per_core": round(1000 / ms, 1) if ms else None})
    return rows


def result(r: dict[str, Any]) -> h.Result:
    p, f = r["pipeline"], r["floor"]
    t = h.Result("pi", f"Deployment table: {r['device']} ({r['machine']}, {r['cores']} cores, "
                 f"{r['size']}; load {r['load_before']} before, {r['load_after']} after)",
                 key="algorithm", data=r)
    for a in r["algorithms"]:
        low, high = a.get("cpu_ms_iqr") or (None, None)
        t.add(a["algorithm"], **{"CPU per pair": h.Figure(a["cpu_ms"], "ms", low, high, 1),
                                 "wall per pair": h.Figure(a["wall_ms"], "ms", digits=1),
                                 "pairs/s per core": h.Figure(a["pairs_per_s_per_core"],
                                                              digits=1)})
    inside = sum(x["process_ms_per_processed"] for x in p["roles"].values())
    total = p["every_pool_cpu_ms"]
    t.notes = [
        f"Per algorithm, alone, one thread, median of {r['pairs']} pairs [interquartile "
        "range].",
        f"Pipeline (mono + stereo + vo) at {r['rate']:g} pairs/s requested, "
        f"{p['capture_hz']} reached: **{total:.1f} ms CPU per pair**, of which "
        f"{inside:.1f} inside the plugins' process(); parallel overhead "
        f"**{total - inside:.1f} ms per pair ({100 * (total - inside) / total:.0f} %)**"
        f" (capture {p['roles']['capture']['cpu_ms']:.1f} ms of it).",
        f"VO floor: **{f['vo_hz']} pairs/s** with the recognisers saturating every "
        f"core (capture {f['capture_hz']} pairs/s; VO dropped {f['vo']['dropped']} of "
        f"{f['vo']['received']}).",
        "A pool keeps up when its workers x pairs/s per core exceeds the rate it gets, "
        "with the overhead's share of the cores left for capture and the broker."]
    return t


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="10 pairs an algorithm, 8 s windows")
    ap.add_argument("--size", default="1280x720", help="camera size WIDTHxHEIGHT")
    ap.add_argument("--pairs", type=int, default=40, help="pairs per algorithm")
    ap.add_argument("--rate", type=float, default=10.0, help="capture rate of the pipeline")
    ap.add_argument("--window", type=float, default=20.0, help="seconds measured per run")
    args = ap.parse_args()
    if args.quick:
        args.pairs, args.window = 10, 8.0
    w, ht = (int(v) for v in args.size.lower().split("x"))
    load0 = os.getloadavg()[0]
    rig = StereoRig.from_fov(w, ht, 70.0, 0.12)
    r: dict[str, Any] = {"device": device(), "machine": platform.machine(),
                         "cores": os.cpu_count(), "size": f"{w}x{ht}", "pairs": args.pairs,
                         "rate": args.rate, "load_before": round(load0, 2)}
    h.log("pi", "per algorithm")
    r["algorithms"] = per_algorithm(rig, args.pairs)
    h.log("pi", "pipeline overhead")
    size = ["--size", f"{w}x{ht}"]
    r["pipeline"] = pipeline_cpu.run_window(["--rate", str(args.rate), *size], 10.0, args.window)
    r["floor"] = pipeline_cpu.part_floor(15.0, 10.0, args.window, size)
    r["load_after"] = round(os.getloadavg()[0], 2)
    results = [result(r)]
    h.write(args.out, "pi", results)
    print(h.markdown(results))


if __name__ == "__main__":
    main()
