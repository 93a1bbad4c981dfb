"""The stereo rig model shared by sources and algorithms: pinhole intrinsics and baseline.

trapflow.sources.rig decides which rig a run uses; this module only models one.
"""

from __future__ import annotations

import hashlib
import math

import msgspec
import numpy as np


class StereoRig(msgspec.Struct, frozen=True, kw_only=True):
    """A rectified stereo rig: both cameras share intrinsics; right = left + baseline along x."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    baseline_m: float

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, baseline_m: float) -> StereoRig:
        """A rig with square pixels and the principal point at the image centre."""
        fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(
            width=width,
            height=height,
            fx=fx,
            fy=fx,
            cx=(width - 1) / 2.0,
            cy=(height - 1) / 2.0,
            baseline_m=baseline_m,
        )

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the images the rig describes."""
        return self.width, self.height

    @property
    def id(self) -> str:
        """A short id of the rig's numbers (8 hex digits): the `calib` of every stereo result.

        BLAKE2b (4-byte digest) of `WxH fx fy cx cy baseline`, pixels to 1e-3 and metres to
        1e-6: parsing noise does not change it, a different calibration does.
        """
        text = (f"{self.width}x{self.height} {self.fx:.3f} {self.fy:.3f} {self.cx:.3f} "
                f"{self.cy:.3f} {self.baseline_m:.6f}")
        return hashlib.blake2b(text.encode("ascii"), digest_size=4).hexdigest()

    def describe(self) -> str:
        """One line for logs and status: size, intrinsics, baseline and id."""
        return (f"{self.width}x{self.height}, fx {self.fx:.1f} fy {self.fy:.1f}, "
                f"cx {self.cx:.1f} cy {self.cy:.1f}, baseline {self.baseline_m:.3f} m "
                f"(calib {self.id})")

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name of the matrix
        """3x3 intrinsic matrix."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    def projection(self, right: bool = False) -> np.ndarray:
        """3x4 projection matrix of the left (P0) or right (P1) camera, KITTI style."""
        p = np.hstack([self.K, np.zeros((3, 1))])
        if right:
            p[0, 3] = -self.fx * self.baseline_m
        return p
