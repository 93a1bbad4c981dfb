"""Seeded MOTChallenge detection files of any size, for `trapflow track`'s memory and speed
checks (tests/reliability/test_track_streams.py, benchmarks/track_memory.py).

Animals cross a 1280x720 frame at constant speed with a little jitter, a few at a time,
each seen for a few seconds; a detection is sometimes missed, and low-confidence clutter
comes and goes. Rows are written frame by frame in frame order, as detectors write them, so
a file of any size is made in bounded memory.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path

WIDTH, HEIGHT = 1280, 720


@dataclass
class _Animal:
    x: float
    y: float
    vx: float
    vy: float
    w: float
    h: float
    cls: int
    frames_left: int


def _spawn(rng: random.Random, fps: float) -> _Animal:
    w, h = rng.uniform(30, 120), rng.uniform(20, 90)
    return _Animal(x=rng.uniform(0, WIDTH - w), y=rng.uniform(0, HEIGHT - h),
                   vx=rng.uniform(-120, 120) / fps, vy=rng.uniform(-60, 60) / fps, w=w, h=h,
                   cls=rng.randrange(3), frames_left=int(rng.uniform(2, 12) * fps))


def frame_lines(frame: int, animals: list[_Animal], rng: random.Random) -> list[str]:
    """One frame's rows: the animals seen (most of them), then clutter."""
    lines = []
    for a in animals:
        if rng.random() < 0.9:
            jx, jy = rng.gauss(0, 1.5), rng.gauss(0, 1.5)
            lines.append(f"{frame},-1,{a.x + jx:.2f},{a.y + jy:.2f},{a.w:.2f},{a.h:.2f},"
                         f"{rng.uniform(0.55, 0.99):.3f},{a.cls}\n")
    for _ in range(rng.randrange(3)):
        lines.append(f"{frame},-1,{rng.uniform(0, WIDTH - 40):.2f},"
                     f"{rng.uniform(0, HEIGHT - 40):.2f},{rng.uniform(10, 40):.2f},"
                     f"{rng.uniform(10, 40):.2f},{rng.uniform(0.1, 0.45):.3f},"
                     f"{rng.randrange(3)}\n")
    return lines


def write_detections(path: Path, size_bytes: int, seed: int = 0, fps: float = 30.0,
                     animals: int = 6) -> int:
    """Write frames of detections to path until it holds at least size_bytes; returns the
    number of frames. The same seed and size give the same file."""
    rng = random.Random(seed)
    live = [_spawn(rng, fps) for _ in range(animals)]
    written, frame = 0, 0
    with open(path, "w", encoding="utf-8") as f:
        while written < size_bytes:
            frame += 1
            text = "".join(frame_lines(frame, live, rng))
            f.write(text)
            written += len(text)
            for i, a in enumerate(live):
                a.x, a.y, a.frames_left = a.x + a.vx, a.y + a.vy, a.frames_left - 1
                if (a.frames_left <= 0 or not -a.w < a.x < WIDTH
                        or not -a.h < a.y < HEIGHT):
                    live[i] = _spawn(rng, fps)
    return frame


# `python -c PEAK_CHILD ARGS...` runs the real trapflow CLI with ARGS and, as it exits, says
# its peak resident memory on stderr (`peak_kib N`, KiB on Linux).
PEAK_CHILD = """
import resource, runpy, sys
sys.argv = ["trapflow", *sys.argv[1:]]
try:
    runpy.run_module("trapflow", run_name="__main__")
finally:
    print("peak_kib", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)
"""
