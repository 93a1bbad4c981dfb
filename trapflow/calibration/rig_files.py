"""Rig files: a KITTI calib.txt, the short YAML a plugin's `calibration` param may name,
or any stereo calibration file; each read into a StereoRig at a given image size."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from trapflow.calibration.camera import StereoRig
from trapflow.calibration.formats import load_calibration
from trapflow.errors import ConfigError

#: fields of the short YAML rig file a plugin's `calibration` param may name
YAML_FIELDS = ("fx", "fy", "cx", "cy", "baseline_m")


def read_kitti_calib(path: Path, size: tuple[int, int]) -> StereoRig:
    """The rig of a KITTI calib.txt (intrinsics from P0, baseline -P1[0,3]/P1[0,0]) at size."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read calibration {path}: {exc.strerror}") from None
    rows: dict[str, list[float]] = {}
    for line in text.splitlines():
        key, sep, rest = line.partition(":")
        if sep:
            try:
                rows[key.strip()] = [float(v) for v in rest.split()]
            except ValueError:
                raise ConfigError(f"calibration {path}: row {key.strip()!r} expected numbers, "
                                  f"got {rest.strip()[:60]!r}") from None
    for key in ("P0", "P1"):
        if key not in rows:
            raise ConfigError(f"calibration {path}: missing field {key} (a row `{key}:` of "
                              "12 numbers, the 3x4 projection of a KITTI calib.txt)")
        if len(rows[key]) != 12:
            raise ConfigError(f"calibration {path}: {key} expected 12 numbers (3x4 "
                              f"projection), got {len(rows[key])}")
    p0 = np.array(rows["P0"]).reshape(3, 4)
    p1 = np.array(rows["P1"]).reshape(3, 4)
    if p0[0, 0] <= 0 or p0[1, 1] <= 0 or p1[0, 0] <= 0 or -p1[0, 3] / p1[0, 0] <= 0:
        raise ConfigError(f"calibration {path}: expected positive focal lengths in P0, P1 and "
                          f"a positive baseline -P1[0,3]/P1[0,0], got P1[0,3]={p1[0, 3]}")
    w, h = size
    return StereoRig(width=w, height=h, fx=float(p0[0, 0]), fy=float(p0[1, 1]),
                     cx=float(p0[0, 2]), cy=float(p0[1, 2]),
                     baseline_m=float(-p1[0, 3] / p1[0, 0]))


def _short_yaml(path: Path, data: dict[str, Any], size: tuple[int, int]) -> StereoRig:
    out: dict[str, float] = {}
    for key in (*YAML_FIELDS, "width", "height"):
        if key not in data:
            if key in YAML_FIELDS:
                raise ConfigError(f"calibration {path}: missing field {key!r} (expected "
                                  f"{', '.join(YAML_FIELDS)}[, width, height])")
            continue
        value = data[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0:
            raise ConfigError(f"calibration {path}: {key} expected a positive number, "
                              f"got {value!r}")
        out[key] = float(value)
    return StereoRig(width=int(out.get("width", size[0])), height=int(out.get("height", size[1])),
                     fx=out["fx"], fy=out["fy"], cx=out["cx"], cy=out["cy"],
                     baseline_m=out["baseline_m"])


def read_rig_file(path: Path, size: tuple[int, int]) -> StereoRig:
    """A rig from a file: a KITTI calib.txt, a short YAML (fx, fy, cx, cy, baseline_m
    [, width, height]) or any stereo calibration load_calibration() reads.

    `size` is the image size when the file does not give one (KITTI, short YAML).
    """
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read calibration {path}: {exc.strerror}") from None
    if any(line.startswith("P0:") for line in text.splitlines()):
        return read_kitti_calib(path, size)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError:
        data = None  # not YAML at all: let load_calibration say what it expected
    if isinstance(data, dict) and "fx" in data:
        return _short_yaml(path, data, size)
    return load_calibration(path).rig()
