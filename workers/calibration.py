"""Rectified stereo calibration for the geometric plugins: from params, a file, or the source's rig.

A calibration file is either a KITTI `calib.txt` (lines `P0: 12 numbers` and
`P1: 12 numbers`; baseline = -P1[0,3] / P1[0,0]) or a YAML mapping with the fields
fx, fy, cx, cy, baseline_m (metres) and optionally width, height (pixels).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from trapflow.camera import StereoRig
from trapflow.errors import WorkerError

YAML_FIELDS = ("fx", "fy", "cx", "cy", "baseline_m")


def _kitti(path: Path, text: str) -> dict[str, float]:
    rows: dict[str, list[float]] = {}
    for line in text.splitlines():
        key, sep, rest = line.partition(":")
        if sep:
            try:
                rows[key.strip()] = [float(v) for v in rest.split()]
            except ValueError:
                raise WorkerError(f"{path}: line {key.strip()!r} is not numbers") from None
    for key in ("P0", "P1"):
        if key not in rows:
            raise WorkerError(f"calibration {path}: missing field {key} (3x4 projection matrix)")
        if len(rows[key]) != 12:
            raise WorkerError(
                f"calibration {path}: {key} expected 12 numbers, got {len(rows[key])}"
            )
    p0, p1 = rows["P0"], rows["P1"]
    if p1[0] <= 0 or -p1[3] / p1[0] <= 0:
        raise WorkerError(f"calibration {path}: P1 gives no positive baseline (P1[0,3]={p1[3]})")
    return {"fx": p0[0], "fy": p0[5], "cx": p0[2], "cy": p0[6], "baseline_m": -p1[3] / p1[0]}


def _yaml(path: Path, text: str) -> dict[str, float]:
    try:
        data: Any = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise WorkerError(f"calibration {path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise WorkerError(f"calibration {path}: expected a mapping of {', '.join(YAML_FIELDS)}")
    out: dict[str, float] = {}
    for key in (*YAML_FIELDS, "width", "height"):
        if key not in data:
            if key in YAML_FIELDS:
                raise WorkerError(f"calibration {path}: missing field {key!r}")
            continue
        value = data[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0:
            raise WorkerError(
                f"calibration {path}: {key} expected a positive number, got {value!r}"
            )
        out[key] = float(value)
    return out


def load_calibration(path: Path, fallback: StereoRig) -> StereoRig:
    """A StereoRig from a calibration file; image size from the file, else from `fallback`."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise WorkerError(f"cannot read calibration {path}: {exc.strerror}") from None
    kitti = any(line.startswith("P0:") for line in text.splitlines())
    values = _kitti(path, text) if kitti else _yaml(path, text)
    return StereoRig(
        width=int(values.get("width", fallback.width)),
        height=int(values.get("height", fallback.height)),
        fx=values["fx"],
        fy=values["fy"],
        cx=values["cx"],
        cy=values["cy"],
        baseline_m=values["baseline_m"],
    )


def resolve_rig(
    calibration: str,
    intrinsics: tuple[float, float, float, float] | None,
    baseline_m: float | None,
    fallback: StereoRig,
) -> StereoRig:
    """The rig a plugin uses: a calibration file, else params' intrinsics, else the source's rig."""
    if calibration:
        return load_calibration(Path(calibration).expanduser(), fallback)
    rig = fallback
    if intrinsics is not None:
        fx, fy, cx, cy = intrinsics
        rig = StereoRig(
            width=rig.width,
            height=rig.height,
            fx=fx,
            fy=fy,
            cx=cx,
            cy=cy,
            baseline_m=rig.baseline_m,
        )
    if baseline_m is not None:
        rig = StereoRig(
            width=rig.width,
            height=rig.height,
            fx=rig.fx,
            fy=rig.fy,
            cx=rig.cx,
            cy=rig.cy,
            baseline_m=baseline_m,
        )
    return rig
