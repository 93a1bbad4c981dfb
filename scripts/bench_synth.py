"""Benchmark of the synthetic world: rendered pairs per second on one core, as JSON.

Usage: python scripts/bench_synth.py [--width 1280 --height 720 --pairs 150 --out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

# One thread for numpy's BLAS too: the variables must be set before numpy loads it.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import cv2  # noqa: E402

from trapflow.calibration.camera import StereoRig  # noqa: E402
from trapflow.synth.options import SynthOptions  # noqa: E402
from trapflow.synth.render import World  # noqa: E402


def bench(width: int, height: int, pairs: int, moving: bool) -> dict[str, float]:
    rig = StereoRig.from_fov(width, height, 70.0, 0.12)
    t0 = time.perf_counter()
    world = World(rig, seed=1, moving=moving, rate_hz=15.0, options=SynthOptions(density=2.0))
    setup = time.perf_counter() - t0
    world.render(0)
    t0 = time.perf_counter()
    for i in range(1, pairs + 1):
        world.render(i)
    dt = time.perf_counter() - t0
    return {"setup_s": round(setup, 3), "pairs_per_s": round(pairs / dt, 2),
            "ms_per_pair": round(1000 * dt / pairs, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--pairs", type=int, default=150)
    ap.add_argument("--out", default="bench-results", help="folder for synth.json and synth.md")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    result = {
        "bench": "synth_render",
        "size": f"{args.width}x{args.height}",
        "threads": cv2.getNumThreads(),
        "static": bench(args.width, args.height, args.pairs, False),
        "moving": bench(args.width, args.height, args.pairs, True),
    }
    text = json.dumps(result, indent=2)
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "synth.json").write_text(text + "\n")
    rows = [f"| {mode} | {result[mode]['pairs_per_s']:.1f} | {result[mode]['ms_per_pair']:.1f} |"
            for mode in ("static", "moving")]
    (out / "synth.md").write_text(
        f"## Synthetic world rendering, {result['size']}, one thread\n\n"
        "| mode | pairs/s | ms per pair |\n|---|---:|---:|\n" + "\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
