"""Stereo rectification computed from K1/D1/K2/D2/R/T, for pinhole and fisheye lenses.

Pure: numbers in, R1/R2/P1/P2/Q out. Pinhole uses cv2.stereoRectify (alpha=0: only valid
pixels). Fisheye takes its rotations from cv2.fisheye.stereoRectify but chooses the new
camera matrix here: OpenCV 5 marks edge pixels beyond the lens model's range with -1e6
when it undistorts them, and its stereoRectify then returns a focal length of 0.002 px
(measured on the kit's 800x503 fisheye pair). Older tools' choices differ wildly on the
same pair (ROS: f 97 px with cx -66; OpenCV 4: f 235 with cx 125), so trapflow keeps
the lenses' own centre resolution instead; see `stereo_rectify`.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import cv2
import numpy as np

Model = Literal["pinhole", "fisheye"]
MODELS: tuple[Model, ...] = ("pinhole", "fisheye")


class Rectification(NamedTuple):
    """Rectifying rotations, rectified projections and the disparity-to-depth matrix."""

    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray


def stereo_rectify(model: Model, k1: np.ndarray, d1: np.ndarray, k2: np.ndarray,
                   d2: np.ndarray, size: tuple[int, int], r: np.ndarray,
                   t: np.ndarray) -> Rectification:
    """Rectification of a calibrated pair (OpenCV conventions, zero disparity at infinity)."""
    t = np.asarray(t, np.float64).reshape(3, 1)
    r = np.asarray(r, np.float64).reshape(3, 3)
    if model == "pinhole":
        r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(
            k1, np.asarray(d1, np.float64).ravel(), k2, np.asarray(d2, np.float64).ravel(),
            size, r, t, flags=cv2.CALIB_ZERO_DISPARITY, alpha=0,
        )
        return Rectification(r1, r2, p1, p2, q)
    d1f = np.asarray(d1, np.float64).reshape(4, 1)
    d2f = np.asarray(d2, np.float64).reshape(4, 1)
    r1, r2, _, _, _ = cv2.fisheye.stereoRectify(k1, d1f, k2, d2f, size, r, t,
                                                cv2.CALIB_ZERO_DISPARITY)
    # A pinhole view of a fisheye cannot hold its whole field: keep the lenses' resolution
    # at the centre (the smaller focal length of the two, so neither eye is upsampled) and
    # put the principal point at the image centre; the periphery beyond is cropped.
    f = float(min(k1[0, 0], k1[1, 1], k2[0, 0], k2[1, 1]))
    w, h = size
    tx = float((r2 @ t)[0, 0])
    return rectified_projections(f, (w - 1) / 2.0, (h - 1) / 2.0, tx, r1, r2)


def rectified_projections(f: float, cx: float, cy: float, tx: float, r1: np.ndarray,
                          r2: np.ndarray) -> Rectification:
    """P1, P2 and Q of a rectified pair whose right camera is at `tx` (< 0) along x."""
    p1 = np.array([[f, 0, cx, 0], [0, f, cy, 0], [0, 0, 1, 0]], np.float64)
    p2 = p1.copy()
    p2[0, 3] = f * tx
    q = np.array([[1, 0, 0, -cx], [0, 1, 0, -cy], [0, 0, 0, f], [0, 0, -1.0 / tx, 0]],
                 np.float64)
    return Rectification(np.asarray(r1, np.float64), np.asarray(r2, np.float64), p1, p2, q)
