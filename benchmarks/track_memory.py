"""Peak memory and time of `trapflow track` on a large seeded detections file.

Writes a MOTChallenge detections file of --size-mb megabytes (tests/kits/motgen.py: 30
animals at a time at 30 fps, with misses and clutter; the same seed gives the same file),
then runs the real CLI on it as a subprocess --repeats times: its peak resident memory
(read by the child itself as it exits), wall time and CPU time (the harness's CPU of this
process's tree, the child ended inside the window), median [min-max]:

    python -m benchmarks.track_memory [--quick] [--repeats 1] [--size-mb 200] [--seed 0]
                                      [--work DIR] [--out bench-results]

--quick: a 5 MB file. The file is kept in --work (default: a temporary folder) and made
again only when missing. Writes track_memory.json and track_memory.md into --out.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import harness as h
from tests.kits.motgen import PEAK_CHILD, write_detections

CHILD = PEAK_CHILD  # the real CLI, saying its peak memory as it exits


def detections(work: Path, size_mb: float, seed: int) -> Path:
    """The detections file of this size and seed, made when missing."""
    work.mkdir(parents=True, exist_ok=True)
    det = work / f"det-{size_mb:g}mb-seed{seed}.txt"
    if not det.exists():
        t0 = time.monotonic()
        frames = write_detections(det, int(size_mb * 1e6), seed=seed, animals=30)
        h.log("track_memory", f"wrote {det} ({det.stat().st_size / 1e6:.1f} MB, {frames} "
              f"frames) in {time.monotonic() - t0:.0f} s")
    return det


def track_once(det: Path, out: Path) -> tuple[float, float, float]:
    """One `trapflow track` run: peak RSS MiB, wall seconds, CPU seconds."""
    cpu0 = h.tree_cpu(os.getpid())
    t0 = time.monotonic()
    res = subprocess.run([sys.executable, "-c", CHILD, "track", str(det), "-o", str(out),
                          "--fps", "30", "--force"], capture_output=True, text=True)
    wall = time.monotonic() - t0
    cpu = h.tree_cpu(os.getpid()) - cpu0
    if res.returncode != 0:
        sys.exit(f"trapflow track failed ({res.returncode}): {res.stderr}")
    peak = [int(x.split()[1]) for x in res.stderr.splitlines() if x.startswith("peak_kib ")]
    return peak[0] / 1024, wall, cpu


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="a 5 MB file")
    ap.add_argument("--size-mb", type=float, default=200.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args()
    size = 5.0 if args.quick else args.size_mb
    work = args.work or Path(tempfile.mkdtemp(prefix="track-mem-"))
    det = detections(work, size, args.seed)
    runs = [track_once(det, work / "tracks.txt") for _ in range(args.repeats)]
    r = h.Result("track_memory", "trapflow track on a large detections file", key="file",
                 notes=[f"Median of {len(runs)} runs [min-max]; seed {args.seed}."],
                 data={"file_mb": round(det.stat().st_size / 1e6, 1), "seed": args.seed,
                       "runs": runs})
    r.add(f"{det.stat().st_size / 1e6:.1f} MB", **{
        "peak RSS": h.figure(h.summarise([x[0] for x in runs]), "MiB", digits=0),
        "wall": h.figure(h.summarise([x[1] for x in runs]), "s", digits=1),
        "CPU": h.figure(h.summarise([x[2] for x in runs]), "s", digits=1)})
    h.write(args.out, "track_memory", [r])
    print(h.markdown([r]))


if __name__ == "__main__":
    main()
