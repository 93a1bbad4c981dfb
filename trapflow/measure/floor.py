"""The sea floor's disparity plane over a whole rectified pair, pure: the slant that an animal
lying on the floor shares, which a small box cannot measure well by itself.

A plane in space is a plane in disparity, d = g + a (u - cx) + b (v - cy); a body lying
parallel to it, raised a little, has the same plane scaled by one factor (its own disparity
at its centre over the floor's there).
"""

from __future__ import annotations

import math

import cv2
import msgspec
import numpy as np

from trapflow.calibration.camera import StereoRig

REDUCTION = 4  # matched at a quarter of the size: a plane over thousands of pixels needs no more
MIN_VALID = 0.25
STEP = 3  # the plane is fitted on every third reduced pixel each way
# Block matching, not semi-global: a third of the CPU, and the robust fit takes its noise
# (development seeds: median length error 2.75 % with 11-pixel blocks, 2.71 % with SGBM).
BLOCK = 11
TEXTURE = 10  # StereoBM's texture threshold: flat patches give no disparity


class FloorPlane(msgspec.Struct, frozen=True, kw_only=True):
    """The floor's disparity plane of one pair (full-size pixels) and its residual spread."""

    g: float  # disparity at the principal point
    a: float  # per pixel along u
    b: float  # per pixel along v
    cx: float
    cy: float
    spread_px: float  # robust sd of the matched pixels about the plane (relief, noise)
    share: float  # share of the image the plane was fitted on

    def at(self, u: float, v: float) -> float:
        """The floor's disparity at pixel (u, v)."""
        return self.g + self.a * (u - self.cx) + self.b * (v - self.cy)


def fit_floor(left: np.ndarray, right: np.ndarray, rig: StereoRig,
              disparities: tuple[int, int]) -> FloorPlane | None:
    """Block matching on the reduced pair, a plane fitted robustly (animals, boulders
    and a relief's bumps are the outliers); None where too little matched or no plane holds
    the matches (a wall, open water). `disparities`: the full-size search limits."""
    k = REDUCTION
    size = (left.shape[1] // k, left.shape[0] // k)
    sl = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
    sr = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
    d_lo = disparities[0] // k
    num = max(16, int(math.ceil((disparities[1] / k - d_lo) / 16.0)) * 16)
    if size[0] < d_lo + num + BLOCK or size[1] < 2 * BLOCK:
        return None  # too small a pair for a search this wide
    bm = cv2.StereoBM.create(numDisparities=num, blockSize=BLOCK)
    bm.setMinDisparity(d_lo)
    bm.setTextureThreshold(TEXTURE)
    bm.setUniquenessRatio(10)
    disp = bm.compute(sl, sr).astype(np.float32) / 16.0
    # every STEP-th reduced pixel each way: a ninth of the points fit as well, and fast
    sub = disp[::STEP, ::STEP]
    vs, us = np.nonzero(sub >= d_lo)
    if us.size < MIN_VALID * sub.size:
        return None
    # reduced pixel centres to full-size pixel coordinates; disparities to full size
    u = (STEP * us + 0.5) * k - 0.5 - rig.cx
    v = (STEP * vs + 0.5) * k - 0.5 - rig.cy
    d = sub[vs, us] * k
    m = np.column_stack([np.ones(d.size), u, v])
    keep = np.ones(d.size, bool)
    coef = np.zeros(3)
    spread = 0.0
    for _ in range(3):  # refit on the inliers of the last fit (3x3 normal equations: fast)
        mk = m[keep]
        coef = np.linalg.solve(mk.T @ mk, mk.T @ d[keep])
        res = d - m @ coef
        spread = 1.4826 * float(np.median(np.abs(res[keep])))
        keep = np.abs(res) <= max(3.0 * spread, 0.5)
    share = float(keep.sum()) / sub.size
    if share < MIN_VALID:
        return None
    return FloorPlane(g=float(coef[0]), a=float(coef[1]), b=float(coef[2]), cx=rig.cx,
                      cy=rig.cy, spread_px=round(spread, 3), share=round(share, 3))


def floor_slopes(floor: FloorPlane, u: float, v: float, d: float) -> tuple[float, float] | None:
    """The disparity slopes (per pixel along u, v) of a body lying parallel to the floor whose
    disparity at (u, v) is d; None where the floor is not in front of the camera there."""
    base = floor.at(u, v)
    if base <= 0:
        return None
    s = d / base
    return s * floor.a, s * floor.b
