"""Rig poses and the moving-mode trajectory of the synthetic world.

Frames: the floor frame F has x east, y north, z up, the mean floor at z = 0.
Cameras follow OpenCV: x right, y down, z forward. A pose is a 4x4
camera-to-frame matrix (a point p_cam maps to R @ p_cam + t).
"""

from __future__ import annotations

import math

import numpy as np

from trapflow.calibration.camera import StereoRig


def rot_z(a: float) -> np.ndarray:
    """Rotation about z by angle a (radians)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def look_rotation(yaw: float, tilt: float, roll: float = 0.0) -> np.ndarray:
    """Camera-to-floor rotation of a camera heading `yaw`, tilted `tilt` below horizontal."""
    ct = math.cos(tilt)
    fwd = np.array([math.cos(yaw) * ct, math.sin(yaw) * ct, -math.sin(tilt)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    r = np.stack([right, down, fwd], axis=1)
    out: np.ndarray = r @ rot_z(roll)
    return out


def make_pose(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from rotation and translation."""
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def inv_pose(m: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


class Trajectory:
    """Left-camera pose in the floor frame as a smooth function of time.

    Static: a fixed tripod. Moving: a figure-of-eight drift (Lissajous) with
    gentle yaw, tilt, roll and height changes, at a mean speed in m/s.
    """

    def __init__(self, *, moving: bool, height_m: float, tilt_deg: float, speed: float,
                 phase: float) -> None:
        self.moving = moving
        self.height = height_m
        self.tilt = math.radians(tilt_deg)
        self.ax, self.ay = 0.9, 0.45
        # The figure of eight is about 6.1 * ax long per period.
        self.omega = speed * 2.0 * math.pi / (6.1 * self.ax)
        self.phase = phase

    def floor_pose(self, t: float) -> np.ndarray:
        """4x4 left-camera-to-floor pose at time t (seconds)."""
        if not self.moving:
            rot = look_rotation(math.pi / 2, self.tilt)
            return make_pose(rot, np.array([0.0, 0.0, self.height]))
        w, p = self.omega, self.phase
        x = self.ax * math.sin(w * t + p)
        y = self.ay * math.sin(2.0 * (w * t + p))
        z = self.height + 0.04 * math.sin(0.7 * w * t + 1.0)
        yaw = math.pi / 2 + 0.25 * math.sin(0.5 * w * t + 0.3)
        tilt = self.tilt + math.radians(3.0) * math.sin(1.3 * w * t)
        roll = math.radians(2.0) * math.sin(1.7 * w * t + 0.5)
        return make_pose(look_rotation(yaw, tilt, roll), np.array([x, y, z]))

    def sample_times(self, n: int = 240) -> np.ndarray:
        """Times covering one period (static: just t = 0)."""
        if not self.moving:
            return np.zeros(1)
        return np.linspace(0.0, 2.0 * math.pi / self.omega, n, endpoint=False)


def right_of(left_pose: np.ndarray, rig: StereoRig) -> np.ndarray:
    """Right-camera pose from the left one: the baseline runs along the left camera's x."""
    off = make_pose(np.eye(3), np.array([rig.baseline_m, 0.0, 0.0]))
    out: np.ndarray = left_pose @ off
    return out


def pixel_rays(rig: StereoRig, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """Camera-frame ray directions with z = 1 for pixel coordinates (..., 3)."""
    return np.stack([(us - rig.cx) / rig.fx, (vs - rig.cy) / rig.fy, np.ones_like(us)], axis=-1)


def floor_points(rig: StereoRig, pose: np.ndarray, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """Where pixel rays meet the plane z = 0 (for planning; NaN where they miss)."""
    d = pixel_rays(rig, us, vs) @ pose[:3, :3].T
    c = pose[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[..., 2] < -1e-3, -c[2] / d[..., 2], np.nan)
    out: np.ndarray = c + t[..., None] * d
    return out
