"""Which source the config names: build_source() picks and builds it; open_source() adds
rectification with the run's calibration, when it has one."""

from __future__ import annotations

from trapflow.calibration.camera import StereoRig
from trapflow.calibration.model import StereoCalibration
from trapflow.config.schema import SourceConfig
from trapflow.errors import ConfigError
from trapflow.sources.base import Source

KINDS = ("synthetic", "video", "images", "v4l2", "picamera2", "gst", "replay")


def build_source(cfg: SourceConfig, rig: StereoRig) -> Source:
    """The source the config names, unopened and without rectification."""
    if cfg.kind not in KINDS:
        raise ConfigError(f"source.kind: expected one of {', '.join(KINDS)}, got {cfg.kind!r}")
    return _build(cfg, rig)


def _build(cfg: SourceConfig, rig: StereoRig) -> Source:
    # Imports are lazy so that a missing optional dependency only matters to its own kind.
    if cfg.kind == "synthetic":
        from trapflow.sources.synthetic import SyntheticSource

        return SyntheticSource(cfg, rig)
    if cfg.kind == "video":
        from trapflow.sources.video import VideoSource

        return VideoSource(cfg, rig)
    if cfg.kind == "images":
        from trapflow.sources.images import ImagesSource

        return ImagesSource(cfg, rig)
    if cfg.kind == "v4l2":
        from trapflow.sources.v4l2 import V4L2Source

        return V4L2Source(cfg, rig)
    if cfg.kind == "picamera2":
        from trapflow.sources.picamera2 import Picamera2Source

        return Picamera2Source(cfg, rig)
    if cfg.kind == "gst":
        from trapflow.sources.gst import GstSource

        return GstSource(cfg, rig)
    if cfg.kind == "replay":
        from trapflow.sources.replay import ReplaySource

        return ReplaySource(cfg, rig)
    raise ConfigError(f"source.kind: expected one of {', '.join(KINDS)}, got {cfg.kind!r}")


def open_source(cfg: SourceConfig, rig: StereoRig,
                calibration: StereoCalibration | None = None) -> Source:
    """Build (not yet open) the source the config names.

    A calibration (the run's, trapflow.sources.rig.run_calibration decides which) makes every
    pair rectified with maps computed once here; its rig replaces `rig`.
    `rig` is the run's rig (trapflow.sources.rig.resolve), which the source then delivers.
    """
    source = build_source(cfg, rig)
    if calibration is not None:
        from trapflow.sources.rectify import RectifiedSource

        source = RectifiedSource(source, calibration)
    return source
