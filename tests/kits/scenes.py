"""Truthful stereo scenes for tests and benches: a textured sea floor and AprilTags, rendered
through exact plane-induced homographies for known camera poses (OpenCV camera frame:
x right, y down, z forward; poses are camera-to-world 4x4).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from trapflow.calibration.camera import StereoRig


def rot_x(a: float) -> np.ndarray:
    """Rotation about x by a radians."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], float)


def rot_z(a: float) -> np.ndarray:
    """Rotation about z by a radians."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], float)


def pose(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from R and t."""
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, np.asarray(t, float).ravel()
    return m


def floor_texture(size_px: int, seed: int = 0) -> np.ndarray:
    """A multi-scale random texture (grey, uint8): corners at every scale, no repetition."""
    rng = np.random.default_rng(seed)
    acc = np.zeros((size_px, size_px), np.float32)
    for cell, weight in ((64, 0.8), (16, 1.0), (4, 1.0)):
        n = size_px // cell + 2
        noise = rng.random((n, n), dtype=np.float32)
        acc += (
            weight
            * cv2.resize(noise, (n * cell, n * cell), interpolation=cv2.INTER_CUBIC)[
                :size_px, :size_px
            ]
        )
    acc -= acc.min()
    out: np.ndarray = (acc * (255.0 / acc.max())).astype(np.uint8)
    return out


@dataclass
class FloorWorld:
    """A textured plane z=0 (world z up) seen by a down-looking stereo rig."""

    rig: StereoRig
    texture: np.ndarray  # texture pixel (u, v) lies at world (x0 + u*res, y0 + v*res, 0)
    res_m: float
    x0: float
    y0: float

    @classmethod
    def square(
        cls, rig: StereoRig, side_m: float, res_m: float = 0.003, seed: int = 0
    ) -> FloorWorld:
        """A square floor centred on the world origin."""
        n = int(side_m / res_m)
        return cls(rig, floor_texture(n, seed), res_m, -side_m / 2, -side_m / 2)

    def _homography(self, cam_to_world: np.ndarray) -> np.ndarray:
        r_cw = cam_to_world[:3, :3].T
        c = cam_to_world[:3, 3]
        m = np.column_stack([r_cw[:, 0], r_cw[:, 1], -r_cw @ c])
        a = np.array([[self.res_m, 0, self.x0], [0, self.res_m, self.y0], [0, 0, 1]])
        return np.asarray(self.rig.K @ m @ a)

    def render(self, cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Left and right BGR images for a left-camera pose."""
        right = cam_to_world @ pose(np.eye(3), np.array([self.rig.baseline_m, 0, 0]))
        out = []
        for p in (cam_to_world, right):
            g = cv2.warpPerspective(
                self.texture,
                self._homography(p),
                (self.rig.width, self.rig.height),
                flags=cv2.INTER_LINEAR,
            )
            out.append(cv2.cvtColor(g, cv2.COLOR_GRAY2BGR))
        return out[0], out[1]


def looking_down(
    x: float, y: float, height: float, heading: float, pitch: float = 0.3
) -> np.ndarray:
    """Camera-to-world pose of a camera at (x, y, height) looking down, tilted forward by pitch."""
    # heading 0: image up points along world +x.
    base = np.array([[0, -1, 0], [-1, 0, 0], [0, 0, -1]], float)  # columns: camera x, y, z
    r = rot_z(heading) @ base @ rot_x(pitch)
    return pose(r, np.array([x, y, height]))


def circle_path(
    length_m: float, steps: int, radius_m: float, height_m: float = 1.6, wobble_m: float = 0.1
) -> Iterator[np.ndarray]:
    """Poses along an arc of `length_m` (heading tangent), with a gentle height wobble."""
    for i in range(steps):
        s = length_m * i / max(steps - 1, 1)
        a = s / radius_m
        x, y = radius_m * math.sin(a), -radius_m * math.cos(a)
        h = height_m + wobble_m * math.sin(2 * math.pi * s / 7.0)
        yield looking_down(x, y, h, heading=a, pitch=0.3 + 0.05 * math.sin(s))


def tag_image(
    rig: StereoRig,
    tag_id: int,
    size_m: float,
    tag_to_cam: np.ndarray,
    background: int = 90,
    family: int = cv2.aruco.DICT_APRILTAG_36h11,
) -> tuple[np.ndarray, np.ndarray]:
    """A BGR image of one AprilTag with pose tag_to_cam (tag frame: x right, y up, z out of
    the tag), and its four corners in pixels (top-left, top-right, bottom-right, bottom-left)."""
    side = 400
    marker = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(family), tag_id, side)
    margin = side // 4  # white quiet zone around the black border
    canvas = np.full((side + 2 * margin, side + 2 * margin), 255, np.uint8)
    canvas[margin : margin + side, margin : margin + side] = marker
    h = size_m / 2
    corners3d = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], float)
    cam = (tag_to_cam[:3, :3] @ corners3d.T).T + tag_to_cam[:3, 3]
    px = (rig.K @ cam.T).T
    px = px[:, :2] / px[:, 2:3]
    # Pixel centres sit at integer coordinates, so the black square's edges are at -0.5.
    lo, hi = margin - 0.5, margin + side - 0.5
    src = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]], np.float32)
    hmg = cv2.getPerspectiveTransform(src, px.astype(np.float32))
    img = cv2.warpPerspective(
        canvas, hmg, (rig.width, rig.height), flags=cv2.INTER_LINEAR, borderValue=background
    )
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), px
