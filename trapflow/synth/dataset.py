"""Writes a synthetic dataset: a KITTI-odometry stereo sequence plus YOLO labels.

OUT/image_0, image_1 (PNG), calib.txt (P0, P1), poses.txt (3x4 left-camera-to-world,
row major, world = first left camera), times.txt (s); labels/NNNNNN.txt (YOLO:
class cx cy w h normalised), classes.txt, truth.jsonl (the full truth per pair).
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import cv2
import msgspec

from trapflow.camera import StereoRig
from trapflow.errors import ConfigError
from trapflow.messages import Truth, TruthObject
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World

log = logging.getLogger(__name__)

CLASSES = ("crab", "scallop", "tag")
LABEL_MAX_OCCLUDED = 0.7  # objects hidden more than this get no YOLO label
LABEL_MIN_SIDE_PX = 4.0
_OURS = ("image_0", "image_1", "labels", "calib.txt", "poses.txt", "times.txt", "classes.txt",
         "truth.jsonl")


def labelled(truth: Truth) -> list[TruthObject]:
    """The objects a detector should find: visible enough and not tiny."""
    return [o for o in truth.objects if o.label in CLASSES and o.occluded <= LABEL_MAX_OCCLUDED
            and o.box[2] - o.box[0] >= LABEL_MIN_SIDE_PX
            and o.box[3] - o.box[1] >= LABEL_MIN_SIDE_PX]


def yolo_lines(truth: Truth, width: int, height: int) -> list[str]:
    """YOLO label lines (class cx cy w h, normalised) for one left image."""
    lines = []
    for o in labelled(truth):
        x1, y1, x2, y2 = o.box
        lines.append(f"{CLASSES.index(o.label)} {(x1 + x2) / 2 / width:.6f} "
                     f"{(y1 + y2) / 2 / height:.6f} {(x2 - x1) / width:.6f} "
                     f"{(y2 - y1) / height:.6f}")
    return lines


def prepare_dir(out: Path, overwrite: bool) -> None:
    """Create OUT; refuse a non-empty one unless overwrite (then only our entries go)."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"OUT: expected a folder, got an existing file {out}")
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise ConfigError(f"OUT: {out} exists and is not empty; pass --overwrite to replace it")
        for name in _OURS:
            p = out / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    for sub in ("image_0", "image_1", "labels"):
        (out / sub).mkdir(parents=True, exist_ok=True)


def _row(values: list[float]) -> str:
    return " ".join(f"{v:.12e}" for v in values)


def write_synth(out: Path, *, frames: int, seed: int, moving: bool, rig: StereoRig,
                rate_hz: float, options: SynthOptions, overwrite: bool = False) -> dict[str, int]:
    """Render `frames` pairs into OUT; returns counts per label and scene."""
    if frames < 1:
        raise ConfigError(f"--frames: expected at least 1, got {frames}")
    prepare_dir(out, overwrite)
    world = World(rig, seed=seed, moving=moving, rate_hz=rate_hz, options=options)
    (out / "calib.txt").write_text(
        f"P0: {_row(list(rig.projection().reshape(-1)))}\n"
        f"P1: {_row(list(rig.projection(right=True).reshape(-1)))}\n")
    (out / "classes.txt").write_text("".join(c + "\n" for c in CLASSES))
    counts: dict[str, int] = {}
    with open(out / "poses.txt", "w") as poses, open(out / "times.txt", "w") as times, \
            open(out / "truth.jsonl", "w") as truths:
        for i in range(frames):
            left, right, truth = world.render(i)
            name = f"{i:06d}"
            cv2.imwrite(str(out / "image_0" / f"{name}.png"), left)
            cv2.imwrite(str(out / "image_1" / f"{name}.png"), right)
            lines = yolo_lines(truth, rig.width, rig.height)
            (out / "labels" / f"{name}.txt").write_text("".join(s + "\n" for s in lines))
            poses.write(_row(list(truth.pose)) + "\n")
            times.write(f"{i / rate_hz:.6e}\n")
            truths.write(json.dumps(msgspec.to_builtins(
                msgspec.structs.replace(truth, seq=i))) + "\n")
            counts["scene:" + truth.scene_label] = counts.get("scene:" + truth.scene_label, 0) + 1
            for o in labelled(truth):
                counts[o.label] = counts.get(o.label, 0) + 1
    log.info("wrote %d pairs to %s", frames, out)
    return counts
