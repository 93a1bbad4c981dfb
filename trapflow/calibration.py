"""The stereo calibration: its typed fields, loading from the formats people have, saving.

Written by `trapflow calibrate`, read by sources for rectification and by algorithms
(through StereoRig) for intrinsics and baseline. Other formats (ROS camera_info pairs,
Kalibr camchains, OpenCV FileStorage, plain K/D/R/T) are read by calibration_formats.py.
Fields are documented in docs/calibration.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import cv2
import msgspec
import numpy as np
import yaml

from trapflow.calibration_rectify import MODELS, Model, stereo_rectify
from trapflow.camera import StereoRig
from trapflow.errors import ConfigError

Matrix = list[list[float]]
Vector = list[float]
CALIBRATION_VERSION = 1


class StereoCalibration(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """A calibrated stereo pair, OpenCV conventions (right = R * left + T, metres)."""

    version: int = CALIBRATION_VERSION
    model: Model = "pinhole"  # lens: pinhole (k1 k2 p1 p2 [k3..k6]) or fisheye (equidistant k1..k4)
    image_width: Annotated[int, msgspec.Meta(gt=0)]
    image_height: Annotated[int, msgspec.Meta(gt=0)]
    K1: Matrix  # noqa: N815 - OpenCV names
    D1: Vector  # noqa: N815
    K2: Matrix  # noqa: N815
    D2: Vector  # noqa: N815
    R: Matrix
    T: Vector
    R1: Matrix  # noqa: N815
    R2: Matrix  # noqa: N815
    P1: Matrix  # noqa: N815
    P2: Matrix  # noqa: N815
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


def load_calibration(path: str | Path, image_size: tuple[int, int] | None = None
                     ) -> StereoCalibration:
    """Read a stereo calibration in any format calibration_formats.py understands.

    `path` is one file, `LEFT,RIGHT` (a ROS camera_info pair, or OpenCV's intrinsics and
    extrinsics files), or a folder holding them. `image_size` (w, h) is needed only for
    files that do not say it (OpenCV FileStorage output). ConfigError names the file, the
    missing or bad field and the formats understood.
    """
    from trapflow.calibration_formats import read_calibration

    return read_calibration(str(path), image_size)


def parse_trapflow(data: dict[str, object], where: str) -> StereoCalibration:
    """trapflow's own fields, or plain K1/D1/K2/D2/R/T (+ image size) rectified here."""
    if "R1" not in data and all(k in data for k in ("K1", "D1", "K2", "D2", "R", "T")):
        return _from_plain(data, where)
    try:
        return msgspec.convert(data, StereoCalibration)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"calibration {where}: {exc}") from None


def _from_plain(data: dict[str, object], where: str) -> StereoCalibration:
    for key in ("image_width", "image_height"):
        if not isinstance(data.get(key), int):
            raise ConfigError(
                f"calibration {where}: plain K1/D1/K2/D2/R/T needs {key} (an integer, pixels); "
                f"got {data.get(key)!r}; add `image_width: W` and `image_height: H`"
            )
    size = (int(str(data["image_width"])), int(str(data["image_height"])))
    try:
        arrs = {k: np.asarray(data[k], np.float64) for k in ("K1", "D1", "K2", "D2", "R", "T")}
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"calibration {where}: K1/D1/K2/D2/R/T must be numbers: {exc}") from None
    model = data.get("model") or guess_model(arrs["D1"].size)
    if model not in MODELS:
        raise ConfigError(
            f"calibration {where}: model: expected one of {', '.join(MODELS)}, got {model!r}"
        )
    for name, shape in (("K1", (3, 3)), ("K2", (3, 3)), ("R", (3, 3))):
        if arrs[name].shape != shape:
            raise ConfigError(f"calibration {where}: field {name}: expected shape {shape}, "
                              f"got {arrs[name].shape}")
    if arrs["T"].size != 3:
        raise ConfigError(f"calibration {where}: field T: expected 3 numbers, "
                          f"got {arrs['T'].size}")
    try:
        return from_extrinsics(model=model, size=size,
                               k1=arrs["K1"], d1=arrs["D1"], k2=arrs["K2"], d2=arrs["D2"],
                               r=arrs["R"], t=arrs["T"])
    except (ValueError, cv2.error) as exc:
        raise ConfigError(f"calibration {where}: {exc}") from None


def guess_model(n_coefficients: int) -> Model:
    """The lens model a distortion vector implies when the file does not say it.

    Four coefficients are a fisheye's k1..k4: OpenCV's pinhole calibration always writes
    5, 8, 12 or 14, and ROS camera_calibration's fisheye mode writes 4 under `plumb_bob`.
    """
    return "fisheye" if n_coefficients == 4 else "pinhole"


def save_calibration(calib: StereoCalibration, path: str | Path) -> None:
    """Write the calibration as YAML (atomically: a half-written file never replaces a good one)."""
    p = Path(path)
    header = "# trapflow stereo calibration; fields are described in docs/calibration.md\n"
    text = header + yaml.safe_dump(msgspec.to_builtins(calib), sort_keys=False, width=120)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(p)
