"""A second, independent stereo scene for VO conformance: a pitched rig over a rocky sea floor.

Written without trapflow's renderer: every pixel's ray is cast with numpy against an undulating
height field and spherical rocks, and shaded from band-limited procedural textures (multi-octave
value noise, pebbles), Lambert light, underwater attenuation and sensor noise. Left and right are
geometrically exact views of a rectified rig (OpenCV camera frame: x right, y down, z forward;
world z up; poses are camera-to-world 4x4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from trapflow.calibration.camera import StereoRig

# 752x480, about 70 degrees across, principal point off the centre, 11 cm baseline.
RIG = StereoRig(width=752, height=480, fx=540.0, fy=540.0, cx=371.3, cy=243.7, baseline_m=0.11)
ALTITUDE_M = 1.5  # camera above the mean floor
PITCH_DEG = 40.0  # optical axis below the horizon

_WAVES = (  # height field: (amplitude m, wavelength m, direction rad, phase rad)
    (0.07, 9.0, 0.3, 0.0), (0.035, 5.0, 2.1, 1.0), (0.018, 2.7, 4.0, 2.0), (0.005, 1.3, 1.2, 0.5),
)  # fmt: skip
MAX_SLOPE = sum(2 * math.pi * a / lam for a, lam, _, _ in _WAVES)  # 0.16
ATLAS_X, ATLAS_Y = (-14.0, 14.0), (-10.0, 14.0)  # the floor's textured area (m)
TEXEL_M = 0.01
_LIGHT = np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93])
_BETA = np.array([0.10, 0.12, 0.22], np.float32)  # attenuation per metre, B G R (red goes first)
_WATER = np.array([0.32, 0.26, 0.06], np.float32)  # veiling light, B G R


def heading_pitch(yaw: float, pitch: float, roll: float = 0.0) -> np.ndarray:
    """Camera-to-world rotation: optical axis at heading `yaw`, `pitch` below the horizon."""
    cp, sp, cy, sy = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    z = np.array([cp * cy, cp * sy, -sp])
    x = np.array([sy, -cy, 0.0])
    y = np.cross(z, x)
    r = np.column_stack([x, y, z])
    if roll:
        c, s = math.cos(roll), math.sin(roll)
        r = r @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return r


def _smooth(f: np.ndarray) -> np.ndarray:
    return f * f * (3 - 2 * f)


class _Noise:
    """Value noise on a rotated lattice: one octave of the texture."""

    def __init__(self, rng: np.random.Generator, spacing: float) -> None:
        table = rng.random((256, 256), dtype=np.float32) * 2 - 1
        self.table = np.pad(table, ((0, 1), (0, 1)), mode="wrap")  # 257x257: no wrap per lookup
        a = rng.uniform(0, 2 * math.pi)
        self.rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) / spacing
        self.off = rng.uniform(0, 256, 2)
        self.spacing = spacing

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        u = (self.rot[0, 0] * x + self.rot[0, 1] * y + self.off[0]).astype(np.float32)
        v = (self.rot[1, 0] * x + self.rot[1, 1] * y + self.off[1]).astype(np.float32)
        iu, iv = np.floor(u), np.floor(v)
        fu, fv = _smooth(u - iu), _smooth(v - iv)
        i0 = iu.astype(np.int32) & 255
        j0 = (iv.astype(np.int32) & 255) * 257
        t = self.table.ravel()
        t00, t01 = t.take(j0 + i0), t.take(j0 + i0 + 1)
        t10, t11 = t.take(j0 + 257 + i0), t.take(j0 + 257 + i0 + 1)
        a = t00 + fu * (t01 - t00)
        b = t10 + fu * (t11 - t10)
        out: np.ndarray = a + fv * (b - a)
        return out


def _fade(spacing: float, footprint: np.ndarray) -> np.ndarray:
    """Weight of an octave: full when its cells span 4+ pixels, gone below 2 (no aliasing)."""
    return np.clip(spacing / footprint * 0.5 - 1.0, 0.0, 1.0)


@dataclass
class Rock:
    """A spherical rock, partly sunk into the floor."""

    centre: np.ndarray
    radius: float
    tint: np.ndarray


class Seafloor:
    """The world: floor height field, rocks, textures; renders exact rectified stereo pairs."""

    def __init__(self, seed: int, rocks: int = 220) -> None:
        rng = np.random.default_rng(seed)
        self.rock_octaves = [(_Noise(rng, 0.4 / 2**k), 0.7**k) for k in range(6)]
        self.levels = self._floor_atlas(rng)
        self.rocks: list[Rock] = []
        (x0, x1), (y0, y1) = ATLAS_X, ATLAS_Y
        for _ in range(rocks):
            x, y = rng.uniform(x0 + 1, x1 - 1), rng.uniform(y0 + 1, y1 - 1)
            r = float(rng.choice([rng.uniform(0.08, 0.2), rng.uniform(0.2, 0.55)], p=[0.7, 0.3]))
            z = float(self.height(np.array([x]), np.array([y]))[0]) + r * rng.uniform(-0.2, 0.4)
            tint = rng.uniform(0.45, 0.9, 3).astype(np.float32) * np.float32([0.8, 1.0, 0.9])
            self.rocks.append(Rock(np.array([x, y, z]), r, tint))
        h, w = RIG.height, RIG.width
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        d = np.stack([(u - RIG.cx) / RIG.fx, (v - RIG.cy) / RIG.fy, np.ones_like(u)], -1)
        self.rays = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3)
        self.rays = self.rays.astype(np.float32)  # 1e-7 rad: a micrometre at 10 m

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Floor height (m) at world x, y."""
        return self._height_grad(x, y)[0]

    def _height_grad(self, x: np.ndarray, y: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # float32: a height error below 1e-7 m, far under a pixel, at half the cost
        x, y = x.astype(np.float32), y.astype(np.float32)
        z, gx, gy = np.zeros_like(x), np.zeros_like(x), np.zeros_like(x)
        for a, lam, ang, ph in _WAVES:
            k = 2 * math.pi / lam
            arg = np.float32(k * math.cos(ang)) * x + np.float32(k * math.sin(ang)) * y
            arg += np.float32(ph)
            z += np.float32(a) * np.sin(arg)
            c = np.cos(arg)
            gx += np.float32(a * k * math.cos(ang)) * c
            gy += np.float32(a * k * math.sin(ang)) * c
        return z, gx, gy

    def _floor_hit(self, c: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Ray parameter of the first floor hit, exact to 1e-6 m.

        Every ray descends more steeply than the floor can rise (checked), so
        c_z + t d_z - h(t) falls monotonically along a ray and Newton's method converges."""
        if d[:, 2].max() >= -MAX_SLOPE * 1.05:
            raise ValueError(f"a ray descends by only {-d[:, 2].max():.3f}: pitch the rig down")
        t = (0.0 - c[2]) / d[:, 2]
        for _ in range(4):
            x, y = c[0] + t * d[:, 0], c[1] + t * d[:, 1]
            h, gx, gy = self._height_grad(x, y)
            f = c[2] + t * d[:, 2] - h
            t = t - f / (d[:, 2] - gx * d[:, 0] - gy * d[:, 1])
        if np.abs(f).max() > 1e-3:  # quadratic convergence: the last step is far smaller
            raise ValueError(f"floor intersection did not converge ({np.abs(f).max():.2g} m)")
        return t

    def _floor_atlas(self, rng: np.random.Generator) -> list[np.ndarray]:
        """The floor's shaded albedo on a 1 cm grid and its mip levels (each half the last).

        Value noise from 2 m down to 3 cm cells plus a per-texel grain, dark and pale pebbles
        drawn anti-aliased, and Lambert shading of the height field baked in."""
        (x0, x1), (y0, y1) = ATLAS_X, ATLAS_Y
        w, h = round((x1 - x0) / TEXEL_M), round((y1 - y0) / TEXEL_M)
        acc = np.zeros((h, w), np.float32)
        for k, amp in enumerate((1.0, 0.8, 0.65, 0.55, 0.5, 0.45, 0.4)):
            cell = 2.0 / 2**k
            lattice = rng.random((int(h * TEXEL_M / cell) + 2, int(w * TEXEL_M / cell) + 2),
                                 dtype=np.float32)
            acc += amp * (cv2.resize(lattice, (w, h), interpolation=cv2.INTER_CUBIC) - 0.5)
        acc += 0.3 * (rng.random((h, w), dtype=np.float32) - 0.5)
        grey = np.clip(0.55 + 0.3 * acc, 0.05, 1.0)
        for factor, count, rmax in ((0.45, 5000, 0.05), (1.45, 3500, 0.04), (0.6, 400, 0.09)):
            mask = np.zeros((h, w), np.uint8)
            for cx, cy, r in zip(rng.uniform(0, w, count), rng.uniform(0, h, count),
                                 rng.uniform(0.012, rmax, count) / TEXEL_M, strict=True):
                cv2.circle(mask, (int(cx * 16), int(cy * 16)), int(r * 16), 255, -1,
                           cv2.LINE_AA, shift=4)
            grey *= 1 + (factor - 1) * mask.astype(np.float32) / 255
        gy, gx = np.mgrid[0:h, 0:w].astype(np.float32)
        _, dx, dy = self._height_grad(x0 + (gx + 0.5) * TEXEL_M, y0 + (gy + 0.5) * TEXEL_M)
        n = np.stack([-dx, -dy, np.ones_like(dx)], -1)
        shade = 0.35 + 0.65 * np.clip(n @ _LIGHT.astype(np.float32) / np.linalg.norm(n, axis=-1),
                                      0, 1)
        levels = [np.clip(grey * shade, 0, 1.2).astype(np.float32)]
        while len(levels) < 6:
            levels.append(cv2.pyrDown(levels[-1]))
        return levels

    def _floor_colour(self, x: np.ndarray, y: np.ndarray, fp: np.ndarray) -> np.ndarray:
        """Trilinear look-up in the atlas: the mip level whose texel matches the footprint."""
        shape = (RIG.height, RIG.width)
        u0 = ((x - ATLAS_X[0]) / TEXEL_M - 0.5).reshape(shape).astype(np.float32)
        v0 = ((y - ATLAS_Y[0]) / TEXEL_M - 0.5).reshape(shape).astype(np.float32)
        level = np.clip(np.log2(fp / TEXEL_M), 0, len(self.levels) - 1.001).reshape(shape)
        base = np.floor(level)
        frac = (level - base).astype(np.float32)
        grey = np.zeros(shape, np.float32)
        for k, img in enumerate(self.levels):
            wk = np.where(base == k, 1 - frac, 0) + np.where(base == k - 1, frac, 0)
            if not wk.any():
                continue
            s = np.float32(0.5**k)  # pyrDown: pixel j of level k sits on pixel j * 2**k
            mu, mv = u0 * s, v0 * s
            grey += wk * cv2.remap(img, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        sand = np.float32([0.55, 0.72, 0.80])  # B G R
        out: np.ndarray = grey.reshape(-1, 1) * sand
        return out

    def _rock_colour(self, p: np.ndarray, n: np.ndarray, fp: np.ndarray, tint: np.ndarray
                     ) -> np.ndarray:
        acc = np.zeros(len(p), np.float32)
        x, y = p[:, 0] + 0.7 * p[:, 2], p[:, 1] - 1.3 * p[:, 2]
        for noise, amp in self.rock_octaves:
            w = _fade(noise.spacing, fp)
            if w.any():
                acc += amp * w * noise(x, y)
        shade = 0.3 + 0.7 * np.clip(n @ _LIGHT, 0, 1)
        out: np.ndarray = (np.clip(0.5 + 0.4 * acc, 0.05, 1) * shade)[:, None] * tint
        return out.astype(np.float32)

    def _rock_box(self, rc: np.ndarray, radius: float) -> tuple[int, int, int, int]:
        """Pixel box (u0, u1, v0, v1) that holds a sphere centred at rc (camera frame)."""
        h, w = RIG.height, RIG.width
        if rc[2] <= 1.5 * radius:  # close or beside the camera: test every pixel
            return 0, w, 0, h
        cube = rc + radius * np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        u = cube[:, 0] / cube[:, 2] * RIG.fx + RIG.cx
        v = cube[:, 1] / cube[:, 2] * RIG.fy + RIG.cy
        return (max(int(u.min()), 0), min(int(u.max()) + 2, w),
                max(int(v.min()), 0), min(int(v.max()) + 2, h))

    def render_view(self, cam_to_world: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """One BGR uint8 image from a camera pose."""
        h, w = RIG.height, RIG.width
        r, c = cam_to_world[:3, :3], cam_to_world[:3, 3].astype(np.float32)
        d = self.rays @ r.T.astype(np.float32)
        t = self._floor_hit(c, d).reshape(h, w)
        d3 = d.reshape(h, w, 3)
        centres = np.array([rock.centre for rock in self.rocks])
        in_cam = (centres - cam_to_world[:3, 3]) @ r
        seen = []  # (rock, its pixels' box, which of them it owns)
        for i in np.flatnonzero((in_cam[:, 2] > -0.6) & (np.linalg.norm(in_cam, axis=1) < 15)):
            rock = self.rocks[i]
            u0, u1, v0, v1 = self._rock_box(in_cam[i], rock.radius)
            if u0 >= u1 or v0 >= v1:
                continue
            oc = (c - rock.centre).astype(np.float32)
            b = d3[v0:v1, u0:u1] @ oc
            disc = b * b - (oc @ oc - rock.radius**2)
            tr = -b - np.sqrt(np.maximum(disc, 0))
            tb = t[v0:v1, u0:u1]
            closer = (disc > 0) & (tr > 0) & (tr < tb)
            if closer.any():
                tb[closer] = tr[closer]
                for _, box, owned in seen:  # a nearer rock takes pixels from farther ones
                    if box[0] < u1 and u0 < box[1] and box[2] < v1 and v0 < box[3]:
                        owned[...] = owned & ~_paste(closer, (u0, v0), box)
                seen.append((rock, (u0, u1, v0, v1), closer))
        p = (c + t[..., None] * d3).reshape(-1, 3)
        t = t.ravel()
        fp = t / RIG.fx / np.maximum(np.abs(d[:, 2]), 0.2)  # the floor is near horizontal
        out = self._floor_colour(p[:, 0], p[:, 1], fp).reshape(h, w, 3)
        for rock, (u0, u1, v0, v1), owned in seen:
            if not owned.any():
                continue
            idx = (np.arange(v0, v1)[:, None] * w + np.arange(u0, u1))[owned]
            n = (p[idx] - rock.centre) / rock.radius
            cos = np.maximum(np.abs(np.sum(n * d[idx], axis=1)), 0.2)
            out[v0:v1, u0:u1][owned] = self._rock_colour(p[idx], n, t[idx] / RIG.fx / cos,
                                                         rock.tint)
        fog = np.exp(-t.reshape(h, w, 1) * _BETA)
        img = (out * fog + _WATER * (1 - fog)) * np.float32(255)
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(1.5)
        return np.clip(img, 0, 255).astype(np.uint8)

    def render(self, cam_to_world: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """The rectified pair of a left-camera pose; the right camera sits baseline along x."""
        right = cam_to_world.copy()
        right[:3, 3] += cam_to_world[:3, 0] * RIG.baseline_m
        rng = np.random.default_rng(seed)
        return self.render_view(cam_to_world, rng), self.render_view(right, rng)


def _paste(mask: np.ndarray, at: tuple[int, int], box: tuple[int, int, int, int]
           ) -> np.ndarray:
    """`mask` (top-left pixel at `at`) cut and padded to the pixel box `box`."""
    u0, u1, v0, v1 = box
    out = np.zeros((v1 - v0, u1 - u0), bool)
    x0, y0 = max(at[0], u0), max(at[1], v0)
    x1, y1 = min(at[0] + mask.shape[1], u1), min(at[1] + mask.shape[0], v1)
    if x0 < x1 and y0 < y1:
        out[y0 - v0 : y1 - v0, x0 - u0 : x1 - u0] = mask[y0 - at[1] : y1 - at[1],
                                                          x0 - at[0] : x1 - at[0]]
    return out


def _pose(x: float, y: float, z: float, yaw: float, pitch: float, roll: float) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = heading_pitch(yaw, pitch, roll)
    out[:3, 3] = (x, y, z)
    return out


def s_curve(length_m: float, step_m: float) -> list[np.ndarray]:
    """An S-curve: heading swings 35 degrees left then right, with a slow bob and a little roll."""
    out, x, y = [], -length_m / 2, -1.0
    n = int(round(length_m / step_m)) + 1
    for i in range(n):
        s = i * step_m
        yaw = math.radians(35) * math.sin(2 * math.pi * s / length_m)
        z = ALTITUDE_M + 0.15 * math.sin(2 * math.pi * s / 7.0)
        pitch = math.radians(PITCH_DEG + 3 * math.sin(2 * math.pi * s / 5.0))
        out.append(_pose(x, y, z, yaw, pitch, math.radians(2.0) * math.sin(s)))
        x, y = x + step_m * math.cos(yaw), y + step_m * math.sin(yaw)
    return out


def arc(length_m: float, step_m: float, radius_m: float = 5.0) -> list[np.ndarray]:
    """A constant left turn of `radius_m` (115 degrees over 10 m), looking a little further."""
    out = []
    n = int(round(length_m / step_m)) + 1
    for i in range(n):
        s = i * step_m
        a = s / radius_m - math.pi / 2
        x, y = radius_m * math.cos(a) - 2.0, radius_m * math.sin(a) + 3.0
        z = ALTITUDE_M + 0.1 * math.sin(2 * math.pi * s / 4.0)
        out.append(_pose(x, y, z, a + math.pi / 2, math.radians(PITCH_DEG - 2), 0.0))
    return out


SEQUENCES = {"s_curve": (s_curve, 11), "arc": (arc, 23)}


def sequence(name: str, cache: Path, length_m: float = 10.0, step_m: float = 0.125
             ) -> tuple[list[np.ndarray], list[Path]]:
    """Ground-truth poses and the PNG pairs of one sequence, rendered once into `cache`."""
    make, seed = SEQUENCES[name]
    poses = make(length_m, step_m)
    world = Seafloor(seed)
    files = []
    for i, pose in enumerate(poses):
        f = cache / f"{name}_{i:04d}.png"
        if not f.exists():
            left, right = world.render(pose, seed * 100003 + i)
            cv2.imwrite(str(f), np.hstack([left, right]), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        files.append(f)
    return poses, files


def load_pair(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Left and right BGR images of a cached pair."""
    both = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return both[:, : RIG.width], both[:, RIG.width :]
