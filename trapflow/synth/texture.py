"""The sea floor: a colour (albedo) texture with baked shading and a smooth height field.

Sand ripples, pebbles, rocks, shell fragments and algae patches are drawn into a
texture in floor coordinates; the low-frequency relief is real geometry (see
Floor.height_at), the small-scale relief is shading only (a few mm, sub-pixel parallax).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

TEXEL_M = 0.002  # texture resolution on the floor
GEO_CELL_M = 0.01  # resolution of the geometric height grid
RELIEF_M = 0.035  # amplitude of the geometric relief


def value_noise(shape: tuple[int, int], cell: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth noise in [0, 1] with features about `cell` texels wide."""
    h, w = shape
    gh, gw = int(h / cell) + 3, int(w / cell) + 3
    grid = rng.random((gh, gw), dtype=np.float32)
    big = cv2.resize(grid, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
    return big[:h, :w]


def fractal(shape: tuple[int, int], cells: list[float], rng: np.random.Generator) -> np.ndarray:
    """Sum of octaves of value noise, normalised to mean 0, std 1."""
    acc = np.zeros(shape, np.float32)
    for i, c in enumerate(cells):
        acc += value_noise(shape, c, rng) * (0.6**i)
    acc -= acc.mean()
    acc /= acc.std() + 1e-6
    return acc


class Floor:
    """A textured sea floor covering [x0, x1] x [y0, y1] metres of the floor frame."""

    def __init__(self, x0: float, x1: float, y0: float, y1: float, rng: np.random.Generator):
        self.x0, self.y1 = x0, y1
        self.wt = int(math.ceil((x1 - x0) / TEXEL_M))
        self.ht = int(math.ceil((y1 - y0) / TEXEL_M))
        gw = int(math.ceil((x1 - x0) / GEO_CELL_M)) + 1
        gh = int(math.ceil((y1 - y0) / GEO_CELL_M)) + 1
        geo = fractal((gh, gw), [60.0, 25.0], rng) * (RELIEF_M / 2.5)
        self.geo = geo.astype(np.float32)
        self.albedo = _paint(self, rng)
        self.albedo4 = cv2.cvtColor(self.albedo, cv2.COLOR_BGR2BGRA)  # 4 channels remap faster

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Geometric floor height (m) at floor coordinates, bilinear."""
        gx = ((x - self.x0) / GEO_CELL_M).astype(np.float32)
        gy = ((self.y1 - y) / GEO_CELL_M).astype(np.float32)
        out: np.ndarray = cv2.remap(self.geo, gx, gy, cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_REPLICATE)
        return out

    def intersect(self, centre: np.ndarray, dirs: np.ndarray, rounds: int = 5) -> np.ndarray:
        """Ray parameter t (float32) where the rays centre + t * dirs meet the relief.

        dirs is (3, rows, cols) in the floor frame. Rays near the horizon are bent
        down to a 1:50 slope so that they land somewhere. Fixed-point iteration on
        z = height(x, y): the relief is gentle, five rounds settle far below a texel.
        """
        inv = (-1.0 / np.minimum(dirs[2], np.float32(-0.02))).astype(np.float32)
        c2 = np.float32(centre[2])
        # With t = (c2 - h) * inv, a ray's position on the height grid is p - h * q per axis.
        qx = inv * dirs[0] * np.float32(1.0 / GEO_CELL_M)
        qy = inv * dirs[1] * np.float32(-1.0 / GEO_CELL_M)
        px = qx * c2 + np.float32((centre[0] - self.x0) / GEO_CELL_M)
        py = qy * c2 + np.float32((self.y1 - centre[1]) / GEO_CELL_M)
        h = np.zeros_like(inv)
        gx, gy = np.empty_like(inv), np.empty_like(inv)
        for _ in range(rounds):
            np.subtract(px, np.multiply(h, qx, out=gx), out=gx)
            np.subtract(py, np.multiply(h, qy, out=gy), out=gy)
            h = cv2.remap(self.geo, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        t: np.ndarray = (c2 - h) * inv
        return t

    def texel_map(self, centre: np.ndarray, dirs: np.ndarray, t: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Texture columns and rows (float32) of the points centre + t * dirs.

        Two single-channel maps: resizing and remapping with them is faster than
        with one interleaved 2-channel map.
        """
        mx = t * dirs[0] * np.float32(1.0 / TEXEL_M)
        mx += np.float32((centre[0] - self.x0) / TEXEL_M)
        my = t * dirs[1] * np.float32(-1.0 / TEXEL_M)
        my += np.float32((self.y1 - centre[1]) / TEXEL_M)
        return mx, my

    def texel(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Texture coordinates (column, row) of floor points, as one 2-channel float32 map."""
        out: np.ndarray = np.stack([(x - self.x0) / TEXEL_M, (self.y1 - y) / TEXEL_M],
                                   axis=-1).astype(np.float32)
        return out


def _stamp(height: np.ndarray, albedo: np.ndarray, cx: float, cy: float, rx: float, ry: float,
           ang: float, top: float, colour: np.ndarray, rng: np.random.Generator) -> None:
    """A rounded stone: a dome in the height map and its speckled colour in the albedo."""
    r = int(max(rx, ry)) + 2
    x0, y0 = int(cx) - r, int(cy) - r
    x1, y1 = int(cx) + r + 1, int(cy) + r + 1
    if x0 < 0 or y0 < 0 or x1 > height.shape[1] or y1 > height.shape[0]:
        return
    yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
    dx, dy = xx - cx, yy - cy
    c, s = math.cos(ang), math.sin(ang)
    u, v = (c * dx + s * dy) / rx, (-s * dx + c * dy) / ry
    theta = np.arctan2(v, u)
    wobble = 1.0 + 0.12 * np.sin(3 * theta + rng.uniform(0, 6)) + 0.06 * np.sin(5 * theta)
    q = (u * u + v * v) / (wobble * wobble)
    inside = np.clip((1.0 - q) * 6.0, 0.0, 1.0)[..., None]
    dome = top * np.sqrt(np.clip(1.0 - q, 0.0, 1.0))
    hp = height[y0:y1, x0:x1]
    hp[:] = np.where(q < 1.0, np.maximum(hp, dome), hp)
    speck = 0.8 + 0.4 * rng.random(inside.shape[:2], dtype=np.float32)[..., None]
    ap = albedo[y0:y1, x0:x1]
    ap[:] = ap * (1.0 - inside) + inside * colour * speck


def _shell(albedo: np.ndarray, height: np.ndarray, cx: float, cy: float, r: float, ang: float,
           colour: np.ndarray) -> None:
    """A shell fragment: a ribbed fan, pale, slightly raised."""
    centre = (int(cx), int(cy))
    axes = (max(int(r), 1), max(int(r * 0.85), 1))
    deg = math.degrees(ang)
    col = tuple(float(c) for c in colour)
    cv2.ellipse(albedo, centre, axes, deg, 200, 340, col, -1, cv2.LINE_AA)
    dark = tuple(float(c) * 0.7 for c in colour)
    for k in range(7):
        a = math.radians(deg + 205 + k * 21)
        end = (int(cx + r * math.cos(a)), int(cy + r * math.sin(a)))
        cv2.line(albedo, centre, end, dark, 1, cv2.LINE_AA)
    cv2.ellipse(height, centre, axes, deg, 200, 340, 0.004, -1)


def _paint(floor: Floor, rng: np.random.Generator) -> np.ndarray:
    h, w = floor.ht, floor.wt
    shape = (h, w)
    # Sand: warm grey-beige with blotches and grain (the grain is what trackers latch on to).
    blotch = fractal(shape, [400.0, 120.0], rng)
    grain: np.ndarray = cv2.GaussianBlur(rng.random(shape, dtype=np.float32), (0, 0), 0.8)
    mid = fractal(shape, [14.0, 5.0], rng)
    base = np.array([150.0, 178.0, 196.0], np.float32)  # BGR sand
    shade = 1.0 + 0.10 * blotch + 0.10 * mid + 0.35 * (grain - 0.5)
    albedo: np.ndarray = base * shade[..., None]
    # Darker silty patches and algae film.
    algae = np.clip((fractal(shape, [300.0, 80.0, 20.0], rng) - 0.9) * 1.5, 0.0, 0.7)[..., None]
    albedo = albedo * (1.0 - algae) + algae * np.array([60.0, 95.0, 85.0], np.float32)
    # Ripples: crests across a dominant direction, bent by noise, fading in patches.
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    a = rng.uniform(0, math.pi)
    lam = rng.uniform(30.0, 45.0)  # texels (6-9 cm)
    bend = fractal(shape, [250.0], rng) * 12.0
    phase = (xx * math.cos(a) + yy * math.sin(a) + bend) * (2 * math.pi / lam)
    ripple = np.sin(phase) + 0.35 * np.sin(2 * phase + 1.0)
    fade = np.clip(0.6 + 0.5 * fractal(shape, [350.0], rng), 0.0, 1.0)
    height = (ripple * fade * 0.0025).astype(np.float32)
    del xx, yy, phase, bend
    area_m2 = h * w * TEXEL_M * TEXEL_M
    stones = [(0.004, 0.012, 150), (0.012, 0.035, 35), (0.035, 0.09, 3)]  # radius range, per m2
    for rmin, rmax, per_m2 in stones:
        for _ in range(int(rng.poisson(per_m2 * area_m2))):
            r = rng.uniform(rmin, rmax) / TEXEL_M
            grey = rng.uniform(60, 170)
            tint = rng.normal(0, 5, 3)
            colour = np.clip(np.array([grey * 0.9, grey * 1.0, grey * 1.1]) + tint, 20, 230)
            _stamp(height, albedo, rng.uniform(0, w), rng.uniform(0, h), r,
                   r * rng.uniform(0.6, 1.0), rng.uniform(0, math.pi), r * TEXEL_M * 0.5,
                   colour.astype(np.float32), rng)
    for _ in range(int(rng.poisson(25 * area_m2))):
        colour = np.array(rng.choice([[200, 215, 230], [170, 190, 225], [150, 160, 200],
                                      [215, 215, 215]]), np.float32)
        _shell(albedo, height, rng.uniform(0, w), rng.uniform(0, h),
               rng.uniform(0.008, 0.025) / TEXEL_M, rng.uniform(0, 2 * math.pi), colour)
    # Geometric relief upsampled onto the texture grid, for its shading.
    geo = cv2.resize(floor.geo, (w, h), interpolation=cv2.INTER_LINEAR)
    total = height + geo
    gx = cv2.Sobel(total, cv2.CV_32F, 1, 0, ksize=3) / (8 * TEXEL_M)
    gy = cv2.Sobel(total, cv2.CV_32F, 0, 1, ksize=3) / (8 * TEXEL_M)
    # Light from above and a little from the camera side (south; texture rows grow southwards).
    lx, ly, lz = 0.15, 0.45, 0.88
    lambert = (-gx * lx - gy * ly + lz) / np.sqrt(gx * gx + gy * gy + 1.0)
    lambert = np.clip(lambert / lz, 0.2, 1.4)
    occl = cv2.GaussianBlur(total, (0, 0), 12.0) - total
    ao = np.clip(1.0 - occl * 40.0, 0.55, 1.05)
    shadow_src = np.roll(cv2.GaussianBlur(height, (0, 0), 2.0), (-4, -1), axis=(0, 1))
    shadow = np.clip(1.0 - np.clip(shadow_src - height, 0, None) * 60.0, 0.5, 1.0)
    lit = albedo * (lambert * ao * shadow)[..., None]
    out: np.ndarray = np.clip(lit, 0, 255).astype(np.uint8)
    return out
