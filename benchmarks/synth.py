"""Benchmark of the synthetic world: rendered pairs per second on one core, static and
moving, median of --repeats runs [min-max].

Usage: python -m benchmarks.synth [--quick] [--repeats 3] [--width 1280 --height 720]
       [--pairs 150] [--out bench-results]
Writes synth.json and synth.md into the output folder.
"""

from __future__ import annotations

import os
import time

# One thread for numpy's BLAS too: the variables must be set before numpy loads it.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import cv2  # noqa: E402

from benchmarks import harness as h  # noqa: E402
from trapflow.calibration.camera import StereoRig  # noqa: E402
from trapflow.synth.options import SynthOptions  # noqa: E402
from trapflow.synth.render import World  # noqa: E402


def bench(width: int, height: int, pairs: int, moving: bool) -> tuple[float, float]:
    """Seconds to set the world up and wall seconds per rendered pair."""
    rig = StereoRig.from_fov(width, height, 70.0, 0.12)
    t0 = time.perf_counter()
    world = World(rig, seed=1, moving=moving, rate_hz=15.0, options=SynthOptions(density=2.0))
    setup = time.perf_counter() - t0
    world.render(0)
    t0 = time.perf_counter()
    for i in range(1, pairs + 1):
        world.render(i)
    return setup, (time.perf_counter() - t0) / pairs


def run(width: int, height: int, pairs: int, repeats: int) -> h.Result:
    r = h.Result("synth", f"Synthetic world rendering, {width}x{height}, one thread",
                 key="mode", notes=[f"Median of {repeats} runs of {pairs} pairs [min-max]."],
                 data={"size": f"{width}x{height}", "threads": cv2.getNumThreads(),
                       "pairs": pairs, "machine": h.machine()})
    for mode in ("static", "moving"):
        runs = [bench(width, height, pairs, mode == "moving") for _ in range(repeats)]
        per_pair = h.summarise([s for _, s in runs])
        rate = h.summarise([1 / s for _, s in runs])
        r.add(mode, **{"pairs/s": h.figure(rate, digits=1),
                       "per pair": h.figure(per_pair, "ms", scale=1000, digits=1),
                       "setup": h.figure(h.summarise([t for t, _ in runs]), "s", digits=3)})
    return r


def main() -> None:
    ap = h.options(__doc__, repeats=3, quick_help="50 pairs a run, one run")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--pairs", type=int, default=150)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    pairs, repeats = (50, 1) if args.quick else (args.pairs, args.repeats)
    result = run(args.width, args.height, pairs, repeats)
    h.write(args.out, "synth", [result])
    print(h.markdown([result]))


if __name__ == "__main__":
    main()
