"""Pixel rays through a coarse grid of image cells, turned into floor-frame directions.

The floor and its lighting are smooth at the scale of a few pixels, so they are
ray-cast on such a grid and resampled to full resolution with cv2.resize.
"""

from __future__ import annotations

import math

import numpy as np

from trapflow.calibration.camera import StereoRig


class RayGrid:
    """Camera-frame rays (z = 1) through the centres of `step` x `step` pixel cells.

    Cell centres follow cv2.resize's INTER_LINEAR sampling, so resizing a map
    computed on this grid to the image size lines each value up with its cell.
    """

    def __init__(self, rig: StereoRig, step: int) -> None:
        w, h = rig.width, rig.height
        self.cols, self.rows = math.ceil(w / step), math.ceil(h / step)
        us = (np.arange(self.cols) + 0.5) * (w / self.cols) - 0.5
        vs = (np.arange(self.rows) + 0.5) * (h / self.rows) - 0.5
        self.us, self.vs = np.meshgrid(us, vs)
        self.x = ((self.us - rig.cx) / rig.fx).astype(np.float32)
        self.y = ((self.vs - rig.cy) / rig.fy).astype(np.float32)
        self.length = np.sqrt(self.x * self.x + self.y * self.y + 1.0).astype(np.float32)

    def directions(self, rot: np.ndarray) -> np.ndarray:
        """Ray directions rotated into the floor frame, float32 (3, rows, cols).

        Both cameras of the rig share their rotation, so one call serves a pair.
        """
        r = rot.astype(np.float32)
        out: np.ndarray = (r[:, 0, None, None] * self.x + r[:, 1, None, None] * self.y
                           + r[:, 2, None, None])
        return out


class Frustum:
    """The image's four side planes in the camera frame, to skip what cannot show."""

    NEAR = 0.05  # what comes closer to the lens than this is not drawn (see World._warp)

    def __init__(self, rig: StereoRig, margin_px: float = 4.0) -> None:
        w, h = rig.width, rig.height
        # Plane normals pointing into the image: left, right, top, bottom edges.
        n = np.array([[rig.fx, 0.0, rig.cx], [-rig.fx, 0.0, w - rig.cx],
                      [0.0, rig.fy, rig.cy], [0.0, -rig.fy, h - rig.cy]])
        self.k = np.linalg.norm(n, axis=1)
        self.normals = n / self.k[:, None]
        self.margin_px = margin_px

    def surely_outside(self, centre: np.ndarray, radius: float) -> bool:
        """True if a sphere (camera frame) lies margin_px or more outside the image.

        A point at signed distance s from an edge's plane and at depth z projects
        s * k / z pixels inside that edge, so the sphere is out if even its nearest
        point to the plane, seen at the sphere's largest depth, is margin_px out.
        """
        z = float(centre[2])
        if z + radius < self.NEAR:
            return True
        if z - radius <= self.NEAR:  # straddles the lens plane: let the caller decide
            return False
        s = self.normals @ centre
        return bool(np.any(s + radius < -self.margin_px * (z + radius) / self.k))
