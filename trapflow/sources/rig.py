"""The one place a run's stereo rig is decided, from the best information there is.

In order: a calibration file (rig.calibration or source.options.rectify), the source's
own (a KITTI calib.txt, CameraInfo in a bag), the size of the source's real frames with
the configured field of view, and last the configured size and field of view. The
supervisor resolves it once at preflight and hands it to every node through NodeSpec.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from trapflow.calibration.camera import StereoRig
from trapflow.calibration.model import load_calibration
from trapflow.config.schema import Config
from trapflow.errors import ConfigError
from trapflow.sources.base import Geometry

log = logging.getLogger(__name__)

#: fields of the short YAML rig file a plugin's `calibration` param may name
YAML_FIELDS = ("fx", "fy", "cx", "cy", "baseline_m")


@dataclass(frozen=True)
class Resolved:
    """The run's rig and where it came from (for the log, status and error messages)."""

    rig: StereoRig
    origin: str
    where: str = ""  # what the source's frames are: "images in DIR", a bag's topics


def from_config(cfg: Config, size: tuple[int, int] | None = None) -> StereoRig:
    """The configured field of view and baseline at `size` (default: source.width/height)."""
    w, h = size if size is not None else (cfg.source.width, cfg.source.height)
    return StereoRig.from_fov(w, h, cfg.rig.hfov_deg, cfg.rig.baseline_m)


def calibration_path(cfg: Config) -> str | None:
    """The calibration file the config names (source.options.rectify wins), or None."""
    path = cfg.source.options.get("rectify", cfg.rig.calibration)
    return str(path) if path else None


def mismatch(frames: tuple[int, int], where: str, rig: StereoRig, origin: str) -> str:
    """One line: both sizes and the fix, for a frame that contradicts the rig."""
    (fw, fh), (rw, rh) = frames, rig.size
    if origin.startswith("calibration file"):
        fix = (f"calibrate this camera at {fw}x{fh} (trapflow calibrate) and point "
               "rig.calibration at that file")
    else:
        fix = f"give --size {fw}x{fh} (source.width/height) or a calibration for that size"
    return (f"frames of {where} are {fw}x{fh}, but the rig ({origin}) is {rw}x{rh}: {fix}")


def resolve(cfg: Config, geometry: Geometry) -> Resolved:
    """Decide the rig from a calibration file, the source's geometry, or the config.

    ConfigError when the source's frames contradict a calibration file's image size.
    """
    path = calibration_path(cfg)
    if path:
        calib = load_calibration(path)
        found = Resolved(calib.rig(), f"calibration file {path}")
        if geometry.size is not None and geometry.size != calib.size:
            raise ConfigError(mismatch(geometry.size, geometry.where or cfg.source.kind,
                                       found.rig, found.origin))
        return found
    if geometry.rig is not None:
        return Resolved(geometry.rig, geometry.origin)
    if geometry.size is not None:
        return Resolved(from_config(cfg, geometry.size),
                        f"{geometry.where}'s frame size and rig.hfov_deg, rig.baseline_m")
    return Resolved(from_config(cfg), "source.width/height, rig.hfov_deg and rig.baseline_m")


def describe(cfg: Config) -> Resolved:
    """The rig of the source the config names, asked of the source without opening it."""
    from trapflow.sources import build_source  # sources import the config; keep this lazy

    geometry = build_source(cfg.source, from_config(cfg)).geometry()
    return replace(resolve(cfg, geometry), where=geometry.where)


# --- rig files ---------------------------------------------------------------------------


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
