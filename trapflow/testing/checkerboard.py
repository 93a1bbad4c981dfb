"""Renders checkerboard views through a known stereo rig: ground truth for calibration tests."""

from __future__ import annotations

import cv2
import numpy as np

from trapflow.calibration.camera import StereoRig

_PX_PER_SQUARE = 40


def board_texture(pattern: tuple[int, int]) -> np.ndarray:
    """A board with cols+1 x rows+1 squares and a one-square white quiet zone (grey image)."""
    cols, rows = pattern
    nx, ny = cols + 1, rows + 1
    s = _PX_PER_SQUARE
    tex = np.full(((ny + 2) * s, (nx + 2) * s), 255, np.uint8)
    for y in range(ny):
        for x in range(nx):
            if (x + y) % 2 == 0:
                tex[(y + 1) * s : (y + 2) * s, (x + 1) * s : (x + 2) * s] = 0
    return tex


def _homography(k: np.ndarray, rot: np.ndarray, t: np.ndarray, square_m: float) -> np.ndarray:
    # Texture pixel -> board metres, with the first inner corner at the origin (as OpenCV orders
    # them), then board plane -> image through K [r1 r2 t].
    s = _PX_PER_SQUARE
    to_m = np.array([[square_m / s, 0, -2 * square_m], [0, square_m / s, -2 * square_m], [0, 0, 1]])
    h = k @ np.column_stack([rot[:, 0], rot[:, 1], t]) @ to_m
    return np.asarray(h / h[2, 2])


def render_pair(rig: StereoRig, pattern: tuple[int, int], square_m: float,
                rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Left and right grey views of the board at pose (rvec, tvec) in the left camera frame.

    The right camera sits baseline_m along +x of the left one with parallel axes, so a point
    X_left maps to X_right = X_left - (baseline, 0, 0): OpenCV's T = (-baseline, 0, 0).
    """
    tex = board_texture(pattern)
    rot, _ = cv2.Rodrigues(np.asarray(rvec, np.float64))
    t = np.asarray(tvec, np.float64).reshape(3)
    out = []
    for shift in (0.0, rig.baseline_m):
        h = _homography(rig.K, rot, t - np.array([shift, 0.0, 0.0]), square_m)
        view = cv2.warpPerspective(tex, h, (rig.width, rig.height), flags=cv2.INTER_AREA,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=110)
        out.append(view)
    return out[0], out[1]
