"""Measure thumbnail codecs for the review queue: at 128, 256 and 512 bytes, how often the
shipped detector and scene classifier give a crop's decoded thumbnail the label they give
the crop itself.

Crops: the synthetic world's animals (their true boxes, 20 % margin, at least 32 px) and
tiles of the real-data kit's photos (04_onnx_detectors/images, 02_apriltag36h11's
official photos). Codecs: the shipped shared-header baseline JPEG (trapflow.modem.thumb,
colour 4:2:0 and grey), and whole WebP and AVIF files fitted by side and quality alike
(their own headers travel: a file is one piece, a lost packet loses it). A thumbnail is
scaled back to its crop's size before the models see it. A crop no codec fits in the
budget counts as a disagreement.

    python scripts/measure_thumbs.py [--worlds 4] [--no-real] [--out FILE]
"""

from __future__ import annotations

import argparse
import io
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from PIL import Image
from trapflow_workers.crab_detector import CrabDetector
from trapflow_workers.scene_classifier import SceneClassifier

from trapflow.calibration.camera import StereoRig
from trapflow.modem import thumb
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.testing.kit import make_context, make_pair

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "realdata"
BUDGETS = (128, 256, 512)


def synth_crops(worlds: int) -> list[np.ndarray]:
    rig = StereoRig.from_fov(1280, 720, 70.0, 0.12)
    out: list[np.ndarray] = []
    for seed in range(worlds):
        world = World(rig, seed=100 + seed, moving=False, rate_hz=2.0,
                      options=SynthOptions(density=3.0))
        for i in range(0, 12, 3):
            left, _, truth = world.render(i)
            for obj in truth.objects:
                if obj.label in ("crab", "scallop") and obj.occluded < 0.3:
                    crop = _crop(left, obj.box)
                    if crop is not None:
                        out.append(crop)
    return out


def _crop(img: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray | None:
    x1, y1, x2, y2 = box
    mx, my = 0.2 * (x2 - x1), 0.2 * (y2 - y1)
    h, w = img.shape[:2]
    a, b = max(0, int(x1 - mx)), max(0, int(y1 - my))
    c, d = min(w, int(x2 + mx)), min(h, int(y2 + my))
    if min(c - a, d - b) < 32:
        return None
    return np.ascontiguousarray(img[b:d, a:c])


def real_crops() -> list[np.ndarray]:
    paths = sorted((REAL / "04_onnx_detectors" / "images").glob("*.jpg"))
    paths += sorted((REAL / "02_apriltag36h11" / "official_test_data").glob("*.jpg"))
    out: list[np.ndarray] = []
    for path in paths:
        img = cv2.imread(str(path))
        h, w = img.shape[:2]
        side = min(h, w) // 3
        for y in range(0, h - side + 1, side):
            for x in range(0, w - side + 1, side):
                out.append(np.ascontiguousarray(img[y:y + side, x:x + side]))
    return out


def _pil_codec(fmt: str) -> Callable[[np.ndarray, int], np.ndarray | None]:
    def run(crop: np.ndarray, budget: int) -> np.ndarray | None:
        rgb = Image.fromarray(cv2.cvtColor(crop, cv2.COLOR_BGR2RGB))
        for side in thumb.SIDES:
            scale = side / max(rgb.size)
            small = rgb.resize((max(1, round(rgb.size[0] * scale)),
                                max(1, round(rgb.size[1] * scale))), Image.Resampling.BOX)
            for quality in thumb.QUALITIES:
                buf = io.BytesIO()
                small.save(buf, fmt, quality=quality)
                if buf.tell() <= budget:
                    back = Image.open(io.BytesIO(buf.getvalue())).convert("RGB")
                    return cv2.cvtColor(np.asarray(back), cv2.COLOR_RGB2BGR)
        return None
    return run


def _thumb_codec(colour: bool) -> Callable[[np.ndarray, int], np.ndarray | None]:
    def run(crop: np.ndarray, budget: int) -> np.ndarray | None:
        packets = thumb.fit(crop, budget, colour)
        if not packets:
            return None
        img = thumb.decode(packets)
        return img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    return run


CODECS = {"JPEG, shared header, colour (shipped)": _thumb_codec(True),
          "JPEG, shared header, grey": _thumb_codec(False),
          "WebP (whole file)": _pil_codec("WEBP"),
          "AVIF (whole file)": _pil_codec("AVIF")}


class Models:
    def __init__(self) -> None:
        self.det = CrabDetector()
        self.det.configure({}, make_context(pool="mono"))
        self.clf = SceneClassifier()
        self.clf.configure({}, make_context(pool="stereo"))

    def labels(self, img: np.ndarray) -> tuple[str, str]:
        big = np.ascontiguousarray(img)
        dets = self.det.process(make_pair(big)).detections
        det = max(dets, key=lambda d: d.confidence).label if dets else "none"
        return det, self.clf.process(make_pair(big)).label


def measure(crops: list[np.ndarray], models: Models) -> dict[tuple[str, int], tuple[float, float]]:
    ref = [models.labels(c) for c in crops]
    out: dict[tuple[str, int], tuple[float, float]] = {}
    for name, codec in CODECS.items():
        for budget in BUDGETS:
            same_det = same_clf = 0
            for crop, (det, clf) in zip(crops, ref, strict=True):
                small = codec(crop, budget)
                if small is None:
                    continue
                back = cv2.resize(small, (crop.shape[1], crop.shape[0]),
                                  interpolation=cv2.INTER_LINEAR)
                got = models.labels(back)
                same_det += got[0] == det
                same_clf += got[1] == clf
            out[(name, budget)] = (same_det / len(crops), same_clf / len(crops))
    return out


def table(title: str, n: int, got: dict[tuple[str, int], tuple[float, float]]) -> str:
    head = " | ".join(f"{b} B detector | {b} B classifier" for b in BUDGETS)
    lines = [f"{title} ({n} crops): share of crops whose decoded thumbnail gets the label "
             "the crop gets", "", f"| codec | {head} |",
             "|---|" + "---|" * (2 * len(BUDGETS))]
    for name in CODECS:
        cells = " | ".join(f"{got[(name, b)][0]:.0%} | {got[(name, b)][1]:.0%}"
                           for b in BUDGETS)
        lines.append(f"| {name} | {cells} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", type=int, default=4)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--no-real", action="store_true", help="the synthetic crops only")
    args = ap.parse_args(argv)
    models = Models()
    parts = []
    synth = synth_crops(args.worlds)
    parts.append(table("Synthetic world's animals", len(synth), measure(synth, models)))
    if REAL.is_dir() and not args.no_real:
        real = real_crops()
        parts.append(table("Real-data kit's photos", len(real), measure(real, models)))
    text = "\n".join(parts)
    if args.out:
        args.out.write_text(text)
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
