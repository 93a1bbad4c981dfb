"""The stereo calibration file: its typed fields, YAML load/save and the rig it implies.

Written by `trapflow calibrate`, read by sources for rectification and by algorithms
(through StereoRig) for intrinsics and baseline. Fields are documented in docs/calibration.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import msgspec
import numpy as np
import yaml

from trapflow.camera import StereoRig
from trapflow.errors import ConfigError

Matrix = list[list[float]]
Vector = list[float]
CALIBRATION_VERSION = 1


class StereoCalibration(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """A calibrated stereo pair, OpenCV conventions (right = R * left + T, metres)."""

    version: int = CALIBRATION_VERSION
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


def load_calibration(path: str | Path) -> StereoCalibration:
    """Read a calibration YAML; ConfigError names the file and the missing or bad field."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"cannot read calibration {p}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"calibration {p}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(
            f"calibration {p}: expected a mapping of fields, got {type(data).__name__}"
        )
    try:
        return msgspec.convert(data, StereoCalibration)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"calibration {p}: {exc}") from None


def save_calibration(calib: StereoCalibration, path: str | Path) -> None:
    """Write the calibration as YAML (atomically: a half-written file never replaces a good one)."""
    p = Path(path)
    header = "# trapflow stereo calibration; fields are described in docs/calibration.md\n"
    text = header + yaml.safe_dump(msgspec.to_builtins(calib), sort_keys=False, width=120)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(p)
