"""The rig a geometric plugin computes with: its own `calibration` param, params, or the run's.

The run's rig comes from the source (trapflow.sources.rig decides it, once, for every node); a
plugin's explicit `calibration` file wins. The file may be a KITTI `calib.txt`, a YAML
mapping of fx, fy, cx, cy, baseline_m (metres) and optionally width, height (pixels), or
any stereo calibration trapflow.calibration.model reads; trapflow.calibration.rig_files
parses it.
"""

from __future__ import annotations

from pathlib import Path

import msgspec

from trapflow.plugin import YAML_FIELDS, ConfigError, StereoRig, WorkerError, read_rig_file

__all__ = ["YAML_FIELDS", "load_calibration", "resolve_rig"]


def load_calibration(path: Path, fallback: StereoRig) -> StereoRig:
    """A StereoRig from a calibration file; image size from the file, else from `fallback`."""
    try:
        return read_rig_file(path, fallback.size)
    except ConfigError as exc:
        raise WorkerError(str(exc)) from None


def resolve_rig(
    calibration: str,
    intrinsics: tuple[float, float, float, float] | None,
    baseline_m: float | None,
    fallback: StereoRig,
) -> StereoRig:
    """The rig a plugin uses: a calibration file, else params' intrinsics, else the run's rig."""
    if calibration:
        return load_calibration(Path(calibration).expanduser(), fallback)
    rig = fallback
    if intrinsics is not None:
        fx, fy, cx, cy = intrinsics
        rig = msgspec.structs.replace(rig, fx=fx, fy=fy, cx=cx, cy=cy)
    if baseline_m is not None:
        rig = msgspec.structs.replace(rig, baseline_m=baseline_m)
    return rig
