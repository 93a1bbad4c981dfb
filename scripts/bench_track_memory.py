"""Peak memory and time of `trapflow track` on a large seeded detections file.

Writes a MOTChallenge detections file of --size-mb megabytes (tests/kits/motgen.py: 30
animals at a time at 30 fps, with misses and clutter; the same seed gives the same file),
then runs the real CLI on it as a subprocess and prints its peak resident memory (read by
the child itself as it exits), wall time and CPU time:

    python scripts/bench_track_memory.py [--size-mb 200] [--seed 0] [--work DIR]

The file is kept in --work (default: a temporary folder) and made again only when missing.
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: tests.kits
from tests.kits.motgen import PEAK_CHILD, write_detections

CHILD = PEAK_CHILD  # the real CLI, saying its peak memory as it exits


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size-mb", type=float, default=200.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="track-mem-"))
    work.mkdir(parents=True, exist_ok=True)
    det = work / f"det-{args.size_mb:g}mb-seed{args.seed}.txt"
    if not det.exists():
        t0 = time.monotonic()
        frames = write_detections(det, int(args.size_mb * 1e6), seed=args.seed, animals=30)
        print(f"wrote {det} ({det.stat().st_size / 1e6:.1f} MB, {frames} frames) in "
              f"{time.monotonic() - t0:.0f} s", flush=True)
    out = work / "tracks.txt"
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    res = subprocess.run([sys.executable, "-c", CHILD, "track", str(det), "-o", str(out),
                          "--fps", "30", "--force"], capture_output=True, text=True)
    wall = time.monotonic() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        sys.exit(f"trapflow track failed ({res.returncode}): {res.stderr}")
    peak = [int(x.split()[1]) for x in res.stderr.splitlines() if x.startswith("peak_kib ")]
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    print(res.stdout.strip())
    print(f"file {det.stat().st_size / 1e6:.1f} MB: peak RSS {peak[0] / 1024:.0f} MiB, "
          f"wall {wall:.0f} s, CPU {cpu:.0f} s")


if __name__ == "__main__":
    main()
