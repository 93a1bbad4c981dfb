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

Usage: python scripts/bench_pi.py [--size 1280x720] [--rate 10] [--out bench-results]
(scripts/bench.sh --pi runs it). Writes pi.json and pi.md into --out and prints pi.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: tests.kits
import bench_cpu
from bench_algorithms import PLUGINS, _frames

from trapflow.calibration.camera import StereoRig
from trapflow.testing.kit import make_context, make_pair

#: (row name, pool, params): the detector as shipped (int8) and as fp32
ALGORITHMS = (
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
        rows.append({"algorithm": name, "pool": pool, "cpu_ms": round(ms, 2),
                     "wall_ms": round(float(np.median(wall)), 2),
                     "pairs_per_s_per_core": round(1000 / ms, 1) if ms else None})
    return rows


def markdown(r: dict[str, Any]) -> str:
    p, f = r["pipeline"], r["floor"]
    lines = [f"## Deployment table: {r['device']} ({r['machine']}, {r['cores']} cores, "
             f"{r['size']}; load {r['load_before']} before, {r['load_after']} after)", "",
             f"Per algorithm, alone, one thread, median of {r['pairs']} pairs:", "",
             "| algorithm | CPU ms per pair | wall ms per pair | pairs/s per core |",
             "|---|---:|---:|---:|"]
    lines += [f"| {a['algorithm']} | {a['cpu_ms']:.1f} | {a['wall_ms']:.1f} | "
              f"{a['pairs_per_s_per_core']} |" for a in r["algorithms"]]
    inside = sum(x["process_ms_per_processed"] for x in p["roles"].values())
    total = p["every_pool_cpu_ms"]
    lines += ["", f"Pipeline (mono + stereo + vo) at {r['rate']:g} pairs/s requested, "
              f"{p['capture_hz']} reached: **{total:.1f} ms CPU per pair**, of which "
              f"{inside:.1f} inside the plugins' process(); parallel overhead "
              f"**{total - inside:.1f} ms per pair ({100 * (total - inside) / total:.0f} %)**"
              f" (capture {p['roles']['capture']['cpu_ms']:.1f} ms of it).",
              "", f"VO floor: **{f['vo_hz']} pairs/s** with the recognisers saturating every "
              f"core (capture {f['capture_hz']} pairs/s; VO dropped {f['vo']['dropped']} of "
              f"{f['vo']['received']}).", "",
              "A pool keeps up when its workers x pairs/s per core exceeds the rate it gets, "
              "with the overhead's share of the cores left for capture and the broker."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="1280x720", help="camera size WIDTHxHEIGHT")
    ap.add_argument("--pairs", type=int, default=40, help="pairs per algorithm")
    ap.add_argument("--rate", type=float, default=10.0, help="capture rate of the pipeline")
    ap.add_argument("--window", type=float, default=20.0, help="seconds measured per run")
    ap.add_argument("--out", default="bench-results", help="folder for pi.json and pi.md")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    load0 = os.getloadavg()[0]
    rig = StereoRig.from_fov(w, h, 70.0, 0.12)
    r: dict[str, Any] = {"device": device(), "machine": platform.machine(),
                         "cores": os.cpu_count(), "size": f"{w}x{h}", "pairs": args.pairs,
                         "rate": args.rate, "load_before": round(load0, 2)}
    print("[bench_pi] per algorithm", file=sys.stderr)
    r["algorithms"] = per_algorithm(rig, args.pairs)
    print("[bench_pi] pipeline overhead", file=sys.stderr)
    size = ["--size", f"{w}x{h}"]
    r["pipeline"] = bench_cpu.run_window(["--rate", str(args.rate), *size], 10.0, args.window)
    r["floor"] = bench_cpu.part_floor(15.0, 10.0, args.window, size)
    r["load_after"] = round(os.getloadavg()[0], 2)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "pi.json").write_text(json.dumps(r, indent=1) + "\n")
    md = markdown(r)
    (out / "pi.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
