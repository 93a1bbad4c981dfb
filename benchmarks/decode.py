"""Benchmark: JPEG decode time of one image, OpenCV against simplejpeg (libjpeg-turbo), in
colour, grey and at reduced DCT scales, at 1280x720 and 1920x1080; CPU ms per call, one
thread, median of --repeats batches [min-max].

Usage: python -m benchmarks.decode [--quick] [--repeats 9] [--out bench-results]
Writes decode.json and decode.md into the output folder.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from typing import Any

import cv2

from benchmarks import harness as h
from trapflow.calibration.camera import StereoRig
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.wire import jpeg

SIZES = ((1280, 720), (1920, 1080))


def operations(width: int, height: int) -> dict[str, Callable[[], Any]]:
    """The operations timed, on one rendered image of this size."""
    rig = StereoRig.from_fov(width, height, 70.0, 0.12)
    img = World(rig, seed=1, moving=False, rate_hz=15.0,
                options=SynthOptions(density=2.0)).render(40)[0]
    data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1]
    raw = data.tobytes()
    return {
        "encode cv2": lambda: cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90]),
        "encode trapflow.wire.jpeg": lambda: jpeg.encode(img, 90),
        "cv2 colour": lambda: cv2.imdecode(data, cv2.IMREAD_COLOR),
        "cv2 grey": lambda: cv2.imdecode(data, cv2.IMREAD_GRAYSCALE),
        "cv2 colour 1/2": lambda: cv2.imdecode(data, cv2.IMREAD_REDUCED_COLOR_2),
        "trapflow.wire.jpeg colour": lambda: jpeg.decode(raw),
        "trapflow.wire.jpeg grey": lambda: jpeg.decode(raw, grey=True),
        "trapflow.wire.jpeg colour 1/2": lambda: jpeg.decode(raw, reduce=2),
    }


def run(repeats: int, calls: int) -> h.Result:
    decoder = ("simplejpeg" if importlib.util.find_spec("simplejpeg") is not None
               else "OpenCV (simplejpeg missing)")
    r = h.Result("decode", f"JPEG of one image, CPU ms, one thread (trapflow.wire.jpeg uses "
                 f"{decoder})", key="operation",
                 notes=[f"Median of {repeats} batches of {calls} calls [min-max]."],
                 data={"decoder": decoder, "repeats": repeats, "calls": calls,
                       "machine": h.machine()})
    cols: dict[str, dict[str, h.Figure]] = {}
    for w, hgt in SIZES:
        for name, fn in operations(w, hgt).items():
            samples = [h.per_call(fn, calls) for _ in range(repeats)]
            cols.setdefault(name, {})[f"{w}x{hgt}"] = h.figure(h.summarise(samples), "ms",
                                                                scale=1000)
    for name, figures in cols.items():
        r.add(name, **figures)
    return r


def main() -> None:
    ap = h.options(__doc__, repeats=9, quick_help="5 calls a batch instead of 10")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    result = run(args.repeats, 5 if args.quick else 10)
    h.write(args.out, "decode", [result])
    print(h.markdown([result]))


if __name__ == "__main__":
    main()
