"""Benchmark: JPEG decode time of one image, OpenCV against simplejpeg (libjpeg-turbo), in
colour, grey and at reduced DCT scales, at 1280x720 and 1920x1080; CPU ms, one thread.

Usage: python scripts/bench_decode.py [--repeats 30] [--out bench-results]
Writes decode.json and decode.md into the output folder.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2

from trapflow.calibration.camera import StereoRig
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.wire import jpeg

SIZES = ((1280, 720), (1920, 1080))


def _cpu_ms(fn: Callable[[], Any], repeats: int) -> float:
    fn()
    best = []
    for _ in range(3):  # the best of three batches: the least disturbed by other jobs
        t = time.process_time()
        for _ in range(repeats):
            fn()
        best.append((time.process_time() - t) / repeats)
    return round(1000 * min(best), 2)


def bench(width: int, height: int, repeats: int) -> dict[str, float]:
    rig = StereoRig.from_fov(width, height, 70.0, 0.12)
    img = World(rig, seed=1, moving=False, rate_hz=15.0,
                options=SynthOptions(density=2.0)).render(40)[0]
    data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1]
    raw = data.tobytes()
    out = {
        "encode cv2": _cpu_ms(lambda: cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90]),
                              repeats),
        "encode trapflow.wire.jpeg": _cpu_ms(lambda: jpeg.encode(img, 90), repeats),
        "cv2 colour": _cpu_ms(lambda: cv2.imdecode(data, cv2.IMREAD_COLOR), repeats),
        "cv2 grey": _cpu_ms(lambda: cv2.imdecode(data, cv2.IMREAD_GRAYSCALE), repeats),
        "cv2 colour 1/2": _cpu_ms(lambda: cv2.imdecode(data, cv2.IMREAD_REDUCED_COLOR_2),
                                  repeats),
        "trapflow.wire.jpeg colour": _cpu_ms(lambda: jpeg.decode(raw), repeats),
        "trapflow.wire.jpeg grey": _cpu_ms(lambda: jpeg.decode(raw, grey=True), repeats),
        "trapflow.wire.jpeg colour 1/2": _cpu_ms(lambda: jpeg.decode(raw, reduce=2), repeats),
    }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--out", default="bench-results", help="folder for decode.json, decode.md")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    r: dict[str, Any] = {f"{w}x{h}": bench(w, h, args.repeats) for w, h in SIZES}
    r["decoder"] = ("simplejpeg" if importlib.util.find_spec("simplejpeg") is not None
                    else "OpenCV (simplejpeg missing)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "decode.json").write_text(json.dumps(r, indent=1) + "\n")
    keys = list(r[f"{SIZES[0][0]}x{SIZES[0][1]}"])
    rows = [f"| {k} | " + " | ".join(f"{r[f'{w}x{h}'][k]:.1f}" for w, h in SIZES) + " |"
            for k in keys]
    (out / "decode.md").write_text(
        f"## JPEG of one image, CPU ms, one thread (trapflow.wire.jpeg uses {r['decoder']})\n\n"
        "| operation | " + " | ".join(f"{w}x{h}" for w, h in SIZES) + " |\n|---|"
        + "---:|" * len(SIZES) + "\n" + "\n".join(rows) + "\n")
    print(json.dumps(r))


if __name__ == "__main__":
    main()
