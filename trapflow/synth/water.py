"""The water between the floor and the lens: light, attenuation, backscatter, snow, noise.

Image formation per channel c (BGR), with d the distance along the ray:
    I = albedo * (E_day * T(d) + E_lamp * spot * (1.5 / d)^2 * T(2d)) + B * (1 - T(d)),
T(d) = exp(-beta_c * d); red is absorbed fastest, so far things turn blue-green.
"""

from __future__ import annotations

import cv2
import numpy as np

from trapflow.calibration.camera import StereoRig

BETA = np.array([0.16, 0.09, 0.45], np.float32)  # attenuation per metre (B, G, R)
BACKSCATTER = np.array([125.0, 112.0, 50.0], np.float32)  # veiling light (B, G, R), grey levels
DAYLIGHT = np.array([0.62, 0.62, 0.42], np.float32)  # down-welling light at depth
LAMP = np.array([0.8, 0.85, 0.9], np.float32)  # the trap's lamp, slightly warm
F_SCALE = 100.0  # light factors travel as uint8, F * F_SCALE


class Light:
    """Per-pixel light factor F and backscatter B for a given distance map (coarse grid)."""

    def __init__(self, rig: StereoRig, us: np.ndarray, vs: np.ndarray, haze: float,
                 lamp: float) -> None:
        x = (us - rig.cx) / rig.fx
        y = (vs - rig.cy) / rig.fy
        self.x, self.baseline = x.astype(np.float32), rig.baseline_m
        vign = 1.0 / (1.0 + x * x + y * y) ** 2
        self.sx, sy = 0.55 * rig.width / rig.fx, 0.5 * rig.height / rig.fy
        self.spot_y = np.exp(-(((y - 0.1 * rig.height / rig.fy) / sy) ** 2)).astype(np.float32)
        self.vign = vign.astype(np.float32)[..., None]
        self.lamp = (lamp * LAMP * self.vign).astype(np.float32)
        self.day = (DAYLIGHT * self.vign).astype(np.float32)
        self.back = (BACKSCATTER * min(haze, 1.0) * self.vign).astype(np.float32)
        self.beta = (BETA * haze).astype(np.float32)

    def maps(self, dist: np.ndarray, depth: np.ndarray, right: bool, gain: float
             ) -> tuple[np.ndarray, np.ndarray]:
        """F (multiplies the albedo) and B (added), both float32 HxWx3.

        The one lamp sits midway between the cameras, so both views see the same
        pool of light on the floor (only vignetting differs).
        """
        d = np.clip(dist, 0.05, 50.0).astype(np.float32)[..., None]
        z = np.clip(depth, 0.05, 50.0).astype(np.float32)
        lamp_x = -self.baseline / 2 if right else self.baseline / 2  # lamp in this camera
        lx = (self.x * z - lamp_x) / z
        spot = 0.3 + 0.7 * np.exp(-((lx / self.sx) ** 2)) * self.spot_y
        t1 = np.exp(-self.beta * d)
        fall = np.minimum((1.5 / d) ** 2, 4.0)
        f = (self.day * t1 + self.lamp * (spot[..., None] * fall * t1 * t1)) * np.float32(gain)
        b = self.back * (1.0 - t1) * np.float32(gain)
        return f, b


def to_u8(f: np.ndarray, scale: float) -> np.ndarray:
    """Quantise a non-negative map to uint8 after scaling."""
    out: np.ndarray = np.clip(f * scale + 0.5, 0, 255).astype(np.uint8)
    return out


class Noise:
    """Sensor noise from a precomputed field, cropped at a random offset each frame."""

    PAD = 32

    def __init__(self, height: int, width: int, sigma: float, rng: np.random.Generator):
        self.sigma = sigma
        field = rng.normal(0.0, sigma, (height + self.PAD, width + self.PAD, 3)).astype(np.float32)
        self.pos = np.clip(field, 0, 255).astype(np.uint8)
        self.neg = np.clip(-field, 0, 255).astype(np.uint8)
        self.h, self.w = height, width

    def apply(self, img: np.ndarray, rng: np.random.Generator) -> None:
        if self.sigma <= 0:
            return
        oy, ox = (int(v) for v in rng.integers(0, self.PAD, 2))
        sl = (slice(oy, oy + self.h), slice(ox, ox + self.w))
        cv2.add(img, self.pos[sl], dst=img)
        cv2.subtract(img, self.neg[sl], dst=img)


class Snow:
    """Marine snow: particles drifting in the water around the rig, in 3D."""

    BOX = (np.array([-2.0, -1.0, -1.2]), np.array([4.0, 5.0, 2.2]))  # offset, size (floor frame)

    def __init__(self, density: float, rng: np.random.Generator):
        n = int(400 * density)
        self.p0 = rng.random((n, 3)) * self.BOX[1]
        self.vel = np.array([0.02, 0.01, -0.008]) + rng.normal(0, 0.006, (n, 3))
        self.radius = rng.uniform(0.0008, 0.0025, n)
        self.bright = rng.uniform(0.6, 1.0, n)

    def points(self, t: float, cam_pos: np.ndarray) -> np.ndarray:
        """Particle positions in the floor frame at time t, wrapped in a box around the rig."""
        off, size = self.BOX
        rel = np.mod(self.p0 + self.vel * t - (cam_pos + off), size)
        out: np.ndarray = rel + cam_pos + off
        return out

    def draw(self, img: np.ndarray, rig: StereoRig, world_to_cam: np.ndarray,
             pts: np.ndarray, colour: np.ndarray) -> None:
        if len(pts) == 0:
            return
        pc = pts @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
        keep = pc[:, 2] > 0.15
        pc, rad, br = pc[keep], self.radius[keep], self.bright[keep]
        u = rig.fx * pc[:, 0] / pc[:, 2] + rig.cx
        v = rig.fy * pc[:, 1] / pc[:, 2] + rig.cy
        r = rig.fx * rad / pc[:, 2]
        inside = (u > -8) & (v > -8) & (u < rig.width + 8) & (v < rig.height + 8)
        # Centres and radii in quarter pixels (shift=2), truncated like int().
        xs = (u[inside] * 4).astype(np.int64).tolist()
        ys = (v[inside] * 4).astype(np.int64).tolist()
        rs = np.maximum((np.minimum(r[inside], 5.0) * 4).astype(np.int64), 3).tolist()
        cols = (br[inside, None] * colour[None, :]).tolist()
        for x, y, rad, col in zip(xs, ys, rs, cols, strict=True):
            cv2.circle(img, (x, y), rad, col, -1, cv2.LINE_AA, shift=2)
