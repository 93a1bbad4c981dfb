"""Writes a synthetic dataset: a KITTI-odometry stereo sequence plus detector labels.

OUT/image_0, image_1 (PNG), calib.txt (P0, P1), poses.txt (3x4 left-camera-to-world,
row major, world = first left camera), times.txt (s); labels/NNNNNN.txt (YOLO:
class cx cy w h normalised), classes.txt, truth.jsonl (the full truth per pair).
For training a detector: images/NNNNNN.png (the left images again, hard links where the
file system has them) beside labels/ and data.yaml, the layout Ultralytics reads (it finds
a label by putting labels/ for images/ in the image's path); and coco.json, the same boxes
as COCO instances (bbox x, y, width, height in pixels; image file names relative to OUT).
For trackers: gt/gt.txt, the animals' tracks in MOTChallenge text (frame from 1, id =
TruthObject.id, x, y, w, h, 1, class from 1 as in classes.txt, visibility) and seqinfo.ini.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path
from typing import Any

import cv2
import msgspec
import yaml

from trapflow.calibration.camera import StereoRig
from trapflow.errors import ConfigError
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.wire.messages import Truth, TruthObject

log = logging.getLogger(__name__)

CLASSES = ("crab", "scallop", "tag")
LABEL_MAX_OCCLUDED = 0.7  # objects hidden more than this get no YOLO label
LABEL_MIN_SIDE_PX = 4.0
_OURS = ("image_0", "image_1", "images", "labels", "calib.txt", "poses.txt", "times.txt",
         "classes.txt", "truth.jsonl", "data.yaml", "coco.json", "gt", "seqinfo.ini")


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
    for sub in ("image_0", "image_1", "images", "labels", "gt"):
        (out / sub).mkdir(parents=True, exist_ok=True)


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:  # no hard links here (FAT, another device): a copy
        shutil.copyfile(src, dst)


def data_yaml() -> str:
    """Ultralytics' dataset file: images/ for both splits (split it as the data needs), the
    class names by index. No `path`: Ultralytics then takes the folder data.yaml is in."""
    return yaml.safe_dump({"train": "images", "val": "images",
                           "names": dict(enumerate(CLASSES))}, sort_keys=False)


def coco_annotations(truth: Truth, image_id: int, first_id: int) -> list[dict[str, Any]]:
    """COCO instances of one left image's labelled objects (ids from first_id on)."""
    out = []
    for k, o in enumerate(labelled(truth)):
        x1, y1, x2, y2 = o.box
        out.append({"id": first_id + k, "image_id": image_id,
                    "category_id": CLASSES.index(o.label) + 1,
                    "bbox": [round(x1, 3), round(y1, 3), round(x2 - x1, 3), round(y2 - y1, 3)],
                    "area": round((x2 - x1) * (y2 - y1), 3), "iscrowd": 0})
    return out


def mot_gt_lines(truth: Truth, frame: int) -> list[str]:
    """MOTChallenge ground-truth lines of one pair's labelled animals (tags are left out:
    their ids are AprilTag ids, which would collide with the animals')."""
    return [f"{frame},{o.id},{o.box[0]:.2f},{o.box[1]:.2f},{o.box[2] - o.box[0]:.2f},"
            f"{o.box[3] - o.box[1]:.2f},1,{CLASSES.index(o.label) + 1},{1.0 - o.occluded:.3f}"
            for o in labelled(truth) if o.label != "tag"]


def seqinfo_ini(name: str, frames: int, rate_hz: float, width: int, height: int) -> str:
    """MOTChallenge's sequence description (trackers and scorers read frameRate here)."""
    return (f"[Sequence]\nname={name}\nimDir=image_0\nframeRate={rate_hz:g}\n"
            f"seqLength={frames}\nimWidth={width}\nimHeight={height}\nimExt=.png\n")


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
    coco: dict[str, Any] = {
        "info": {"description": f"trapflow synthetic world, seed {seed}", "version": "1"},
        "images": [], "annotations": [],
        "categories": [{"id": i + 1, "name": c, "supercategory": "object"}
                       for i, c in enumerate(CLASSES)]}
    (out / "seqinfo.ini").write_text(seqinfo_ini(out.name, frames, rate_hz, rig.width,
                                                 rig.height))
    with open(out / "poses.txt", "w") as poses, open(out / "times.txt", "w") as times, \
            open(out / "truth.jsonl", "w") as truths, open(out / "gt" / "gt.txt", "w") as gt:
        for i in range(frames):
            left, right, truth = world.render(i)
            name = f"{i:06d}"
            cv2.imwrite(str(out / "image_0" / f"{name}.png"), left)
            _link_or_copy(out / "image_0" / f"{name}.png", out / "images" / f"{name}.png")
            coco["images"].append({"id": i + 1, "file_name": f"image_0/{name}.png",
                                   "width": rig.width, "height": rig.height})
            coco["annotations"] += coco_annotations(truth, i + 1,
                                                    len(coco["annotations"]) + 1)
            cv2.imwrite(str(out / "image_1" / f"{name}.png"), right)
            lines = yolo_lines(truth, rig.width, rig.height)
            (out / "labels" / f"{name}.txt").write_text("".join(s + "\n" for s in lines))
            gt.write("".join(line + "\n" for line in mot_gt_lines(truth, i + 1)))
            poses.write(_row(list(truth.pose)) + "\n")
            times.write(f"{i / rate_hz:.6e}\n")
            truths.write(json.dumps(msgspec.to_builtins(
                msgspec.structs.replace(truth, seq=i))) + "\n")
            counts["scene:" + truth.scene_label] = counts.get("scene:" + truth.scene_label, 0) + 1
            for o in labelled(truth):
                counts[o.label] = counts.get(o.label, 0) + 1
    (out / "data.yaml").write_text(data_yaml())
    (out / "coco.json").write_text(json.dumps(coco) + "\n")
    log.info("wrote %d pairs to %s", frames, out)
    return counts
