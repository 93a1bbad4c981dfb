"""The stereo calibration: its typed fields, loading from the formats people have, saving.

Written by `trapflow calibrate`, read by sources for rectification and by algorithms
(through StereoRig) for intrinsics and baseline. Other formats (ROS camera_info pairs,
Kalibr camchains, OpenCV FileStorage, plain K/D/R/T) are read by calibration.formats.
Fields are documented in docs/calibration.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import msgspec
import numpy as np
import yaml

from trapflow.calibration.camera import StereoRig
from trapflow.calibration.rectify import MODELS, Model, stereo_rectify

Matrix = list[list[float]]
Vector = list[float]
CALIBRATION_VERSION = 1


class StereoCalibration(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """A calibrated stereo pair, OpenCV conventions (right = R * left + T, metres)."""

    version: int = CALIBRATION_VERSION
    model: Model = "pinhole"  # lens: pinhole (k1 k2 p1 p2 [k3..k6]) or fisheye (equidistant k1..k4)
    image_width: Annotated[int, msgspec.Meta(gt=0)]
    image_height: Annotated[int, msgspec.Meta(gt=0)]
    K1: Matrix  # OpenCV's names (stereoCalibrate, stereoRectify)
    D1: Vector
    K2: Matrix
    D2: Vector
    R: Matrix
    T: Vector
    R1: Matrix
    R2: Matrix
    P1: Matrix
    P2: Matrix
    Q: Matrix
    baseline_m: Annotated[float, msgspec.Meta(gt=0)]
    E: Matrix | None = None
    F: Matrix | None = None
    rms_px: float | None = None
    views_used: int | None = None
    views_rejected: list[str] = []
    pattern: tuple[int, int] | None = None
    square_m: float | None = None

    def __post_init__(self) -> None:
        shapes = {"K1": (3, 3), "K2": (3, 3), "R": (3, 3), "R1": (3, 3), "R2": (3, 3),
                  "P1": (3, 4), "P2": (3, 4), "Q": (4, 4), "T": (3,)}
        for name, shape in shapes.items():
            got = np.asarray(getattr(self, name), dtype=np.float64).shape
            if got != shape:
                raise ValueError(f"field {name}: expected shape {shape}, got {got}")
        for name in ("D1", "D2"):
            n = len(getattr(self, name))
            if self.model == "fisheye" and n != 4:
                raise ValueError(f"field {name}: a fisheye lens has 4 coefficients, got {n}")
            if self.model == "pinhole" and n not in (4, 5, 8, 12, 14):
                raise ValueError(f"field {name}: expected 4, 5, 8, 12 or 14 coefficients, got {n}")

    def arr(self, name: str) -> np.ndarray:
        """A field as a float64 numpy array."""
        return np.asarray(getattr(self, name), dtype=np.float64)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the calibrated images."""
        return self.image_width, self.image_height

    def rig(self) -> StereoRig:
        """The rectified rig: intrinsics of P1, baseline from P2 (what algorithms see)."""
        p1, p2 = self.arr("P1"), self.arr("P2")
        return StereoRig(
            width=self.image_width, height=self.image_height,
            fx=float(p1[0, 0]), fy=float(p1[1, 1]), cx=float(p1[0, 2]), cy=float(p1[1, 2]),
            baseline_m=float(-p2[0, 3] / p2[0, 0]) if p2[0, 0] else self.baseline_m,
        )


def from_extrinsics(*, model: Model, size: tuple[int, int], k1: np.ndarray, d1: np.ndarray,
                    k2: np.ndarray, d2: np.ndarray, r: np.ndarray, t: np.ndarray,
                    **extra: object) -> StereoCalibration:
    """A complete calibration from intrinsics and extrinsics: trapflow rectifies it itself."""
    if model not in MODELS:
        raise ValueError(f"model: expected one of {', '.join(MODELS)}, got {model!r}")
    det = float(np.linalg.det(np.asarray(r, np.float64).reshape(3, 3)))
    if abs(det - 1) > 1e-3:
        raise ValueError(f"R: expected a rotation (det 1), got det {det:.6f}")
    for name, d in (("D1", d1), ("D2", d2)):
        if model == "fisheye" and np.size(d) != 4:
            raise ValueError(f"field {name}: a fisheye lens has 4 coefficients, got {np.size(d)}")
    rect = stereo_rectify(model, k1, d1, k2, d2, size, r, t)
    return StereoCalibration(
        model=model, image_width=size[0], image_height=size[1],
        K1=_m(k1), D1=_v(d1), K2=_m(k2), D2=_v(d2), R=_m(r), T=_v(t),
        R1=_m(rect.R1), R2=_m(rect.R2), P1=_m(rect.P1), P2=_m(rect.P2), Q=_m(rect.Q),
        baseline_m=float(np.linalg.norm(np.asarray(t, np.float64))), **extra,  # type: ignore[arg-type]
    )


def _m(a: np.ndarray) -> Matrix:
    rows = np.asarray(a, np.float64)
    return [[float(v) for v in row] for row in rows.reshape(rows.shape[0], -1)]


def _v(a: np.ndarray) -> Vector:
    return [float(v) for v in np.asarray(a, np.float64).ravel()]


def save_calibration(calib: StereoCalibration, path: str | Path) -> None:
    """Write the calibration as YAML (atomically: a half-written file never replaces a good one)."""
    p = Path(path)
    header = "# trapflow stereo calibration; fields are described in docs/calibration.md\n"
    text = header + yaml.safe_dump(msgspec.to_builtins(calib), sort_keys=False, width=120)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(p)
