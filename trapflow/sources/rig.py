"""The one place a run's stereo rig is decided, from the best information there is.

In order: a calibration file (rig.calibration or source.options.rectify), the source's
own (a KITTI calib.txt, CameraInfo in a bag), the size of the source's real frames with
the configured field of view, and last the configured size and field of view. The
supervisor resolves it once at preflight and hands it to every node through NodeSpec,
with the other fact of the world only the source knows: the size of the tags it lays.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

from trapflow.calibration.camera import StereoRig
from trapflow.calibration.formats import load_calibration
from trapflow.calibration.model import StereoCalibration
from trapflow.config.schema import Config
from trapflow.errors import ConfigError
from trapflow.sources.base import Geometry
from trapflow.sources.factory import build_source

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Resolved:
    """The run's rig and where it came from (for the log, status and error messages)."""

    rig: StereoRig
    origin: str
    where: str = ""  # what the source's frames are: "images in DIR", a bag's topics
    tag_size_m: float | None = None  # the tags the source lays (a synthetic world's), if known


def from_config(cfg: Config, size: tuple[int, int] | None = None) -> StereoRig:
    """The configured field of view and baseline at `size` (default: source.width/height)."""
    w, h = size if size is not None else (cfg.source.width, cfg.source.height)
    return StereoRig.from_fov(w, h, cfg.rig.hfov_deg, cfg.rig.baseline_m)


def calibration_path(cfg: Config) -> str | None:
    """The calibration file that applies, or None: source.options.rectify wins over
    rig.calibration."""
    path = cfg.source.options.get("rectify", cfg.rig.calibration)
    return str(path) if path else None


def run_calibration(cfg: Config) -> StereoCalibration | None:
    """The calibration file that applies, read; None without one. The one place this is
    decided: the supervisor's preflight (the run's rig, through resolve()) and capture (its
    rectification, through open_source) both call it. Each reads the file in its own
    process, a few kilobytes once at start, rather than passing a calibration over a
    process boundary; both read the same file, so they agree."""
    path = calibration_path(cfg)
    return load_calibration(path) if path else None


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
    calib = run_calibration(cfg)
    if calib is not None:
        found = Resolved(calib.rig(), f"calibration file {calibration_path(cfg)}")
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
    """The rig of the source the config names, and the size of the tags it lays, asked of
    the source without opening it."""

    geometry = build_source(cfg.source, from_config(cfg)).geometry()
    return replace(resolve(cfg, geometry), where=geometry.where,
                   tag_size_m=geometry.tag_size_m)
