"""Top-down sprites of what lies or walks on the floor: crabs, scallops, boulders, tags.

A sprite is a premultiplied BGRA float32 image (its body plus a soft contact
shadow) and a body mask (what counts as the animal for its truth box), with its
size in metres. Drawn at twice the resolution and reduced, for smooth edges.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

CRAB_FRAMES = 8  # walking-cycle frames per crab sprite


@dataclass
class Sprite:
    """A flat picture of an object seen from above and how big it is."""

    rgba: np.ndarray  # HxWx4 float32, colour premultiplied by alpha, 0..255 / 0..1
    body: np.ndarray  # HxW float32 in 0..1: the object itself (no shadow)
    size_m: float  # the sprite's side in metres

    @property
    def side(self) -> int:
        return int(self.rgba.shape[0])


def _finish(colour: np.ndarray, body: np.ndarray, shadow: np.ndarray, side: int,
            size_m: float) -> Sprite:
    """Reduce a 2x canvas; combine body and shadow into premultiplied BGRA."""
    colour = cv2.resize(colour, (side, side), interpolation=cv2.INTER_AREA)
    body = cv2.resize(body, (side, side), interpolation=cv2.INTER_AREA)
    shadow = cv2.resize(shadow, (side, side), interpolation=cv2.INTER_AREA)
    alpha = body + (1.0 - body) * shadow
    rgba = np.dstack([colour * body[..., None], alpha]).astype(np.float32)
    return Sprite(rgba=rgba, body=body.astype(np.float32), size_m=size_m)


def _shadow(shape: tuple[int, int], mask: np.ndarray, strength: float, blur: float) -> np.ndarray:
    shifted = np.roll(mask, (int(blur * 0.6), int(blur * 0.2)), axis=(0, 1))
    out: np.ndarray = cv2.GaussianBlur(shifted, (0, 0), blur) * strength
    return out


# --- crabs ------------------------------------------------------------------------

CRAB_PALETTES = [  # BGR carapace, legs: shore crab (olive), edible crab (brick), velvet crab
    ((40, 95, 85), (35, 80, 90)),
    ((60, 100, 170), (70, 120, 185)),
    ((70, 60, 55), (90, 70, 60)),
    ((45, 75, 110), (50, 85, 120)),
]


def crab_frames(rng: np.random.Generator, carapace_m: float, side: int = 160) -> list[Sprite]:
    """A walking cycle of one crab; the front (claws) faces the sprite's top."""
    # Long on purpose: one drawing, stroke by stroke (body, legs, claws, eyes, shading);
    # the strokes share the body's geometry.
    pal = CRAB_PALETTES[int(rng.integers(len(CRAB_PALETTES)))]
    shell = np.array(pal[0], np.float32) * rng.uniform(0.85, 1.15)
    legc = np.array(pal[1], np.float32) * rng.uniform(0.85, 1.15)
    s2 = side * 2
    size_m = carapace_m * 2.8
    cw = s2 / 2.8  # carapace width on the canvas
    c = np.array([s2 / 2, s2 / 2 + cw * 0.05])
    mottle = cv2.GaussianBlur(rng.random((s2, s2), dtype=np.float32), (0, 0), 3.0)
    frames = []
    for f in range(CRAB_FRAMES):
        col = np.zeros((s2, s2, 3), np.float32)
        body = np.zeros((s2, s2), np.float32)
        ph = 2 * math.pi * f / CRAB_FRAMES
        for side_sign in (-1, 1):
            for k in range(4):  # walking legs, alternating gait
                base_ang = math.radians(-25 + 22 * k)
                swing = 0.22 * math.sin(ph + math.pi * ((k + (side_sign > 0)) % 2))
                a = base_ang + swing
                p0 = c + np.array([side_sign * cw * 0.42, cw * (-0.05 + 0.09 * k)])
                d1 = np.array([side_sign * math.cos(a), math.sin(a)])
                p1 = p0 + d1 * cw * 0.38
                a2 = a + 0.9 + 0.1 * k
                d2 = np.array([side_sign * math.cos(a2), math.sin(a2)])
                p2 = p1 + d2 * cw * 0.36
                for q0, q1, th in ((p0, p1, 0.075), (p1, p2, 0.05)):
                    pa = (int(q0[0]), int(q0[1]))
                    pb = (int(q1[0]), int(q1[1]))
                    t = max(int(cw * th), 1)
                    cv2.line(col, pa, pb, tuple(float(v) for v in legc), t, cv2.LINE_AA)
                    cv2.line(body, pa, pb, 1.0, t, cv2.LINE_AA)
            # claw (cheliped): arm forward and in, a heavy propodus, dark fingers
            arm0 = c + np.array([side_sign * cw * 0.36, -cw * 0.22])
            arm1 = arm0 + np.array([side_sign * cw * 0.22, -cw * 0.25])
            claw = arm1 + np.array([-side_sign * cw * 0.12, -cw * 0.16])
            pa, pb = (int(arm0[0]), int(arm0[1])), (int(arm1[0]), int(arm1[1]))
            cv2.line(col, pa, pb, tuple(float(v) for v in legc), int(cw * 0.09), cv2.LINE_AA)
            cv2.line(body, pa, pb, 1.0, int(cw * 0.09), cv2.LINE_AA)
            ctr = (int(claw[0]), int(claw[1]))
            axes = (int(cw * 0.15), int(cw * 0.09))
            ang = -60 * side_sign
            cv2.ellipse(col, ctr, axes, ang, 0, 360, tuple(float(v) * 1.1 for v in shell), -1,
                        cv2.LINE_AA)
            cv2.ellipse(body, ctr, axes, ang, 0, 360, 1.0, -1, cv2.LINE_AA)
            tip = claw + np.array([-side_sign * cw * 0.1, -cw * 0.12])
            cv2.line(col, ctr, (int(tip[0]), int(tip[1])), (25, 25, 30), int(cw * 0.035),
                     cv2.LINE_AA)
        # carapace: wider than long, fronted by teeth, mottled and domed
        ctr = (int(c[0]), int(c[1]))
        axes = (int(cw * 0.5), int(cw * 0.36))
        shell_mask = np.zeros((s2, s2), np.float32)
        cv2.ellipse(shell_mask, ctr, axes, 0, 0, 360, 1.0, -1, cv2.LINE_AA)
        for t in range(9):  # antero-lateral teeth
            a = math.radians(200 + t * 17.5)
            pt = (int(c[0] + cw * 0.5 * math.cos(a)), int(c[1] + cw * 0.37 * math.sin(a)))
            cv2.circle(shell_mask, pt, int(cw * 0.045), 1.0, -1, cv2.LINE_AA)
        yy, xx = np.mgrid[0:s2, 0:s2].astype(np.float32)
        rr = ((xx - c[0]) / (cw * 0.5)) ** 2 + ((yy - c[1] + cw * 0.05) / (cw * 0.36)) ** 2
        dome = np.clip(1.25 - 0.55 * rr, 0.5, 1.25)
        shell_col = shell[None, None, :] * (dome * (0.8 + 0.4 * mottle))[..., None]
        m = shell_mask[..., None]
        col = col * (1 - m) + shell_col * m
        body = np.maximum(body, shell_mask)
        for sgn in (-1, 1):  # eyes on stalks at the front
            e = (int(c[0] + sgn * cw * 0.1), int(c[1] - cw * 0.36))
            cv2.circle(col, e, int(cw * 0.04), (20, 20, 25), -1, cv2.LINE_AA)
            cv2.circle(body, e, int(cw * 0.04), 1.0, -1, cv2.LINE_AA)
        shadow = _shadow((s2, s2), body, 0.45, cw * 0.08)
        frames.append(_finish(col, body, shadow, side, size_m))
    return frames


# --- scallops ---------------------------------------------------------------------

SCALLOP_COLOURS = [(60, 90, 150), (90, 110, 190), (120, 120, 200), (70, 120, 180), (110, 90, 140)]


def scallop_pair(rng: np.random.Generator, diameter_m: float, side: int = 128
                 ) -> tuple[Sprite, Sprite]:
    """One scallop, (closed, open); the hinge (ears) faces the sprite's top."""
    base = np.array(SCALLOP_COLOURS[int(rng.integers(len(SCALLOP_COLOURS)))], np.float32)
    base *= rng.uniform(0.8, 1.15)
    s2 = side * 2
    size_m = diameter_m * 1.6
    r = s2 / 1.6 / 2
    c = (s2 / 2, s2 / 2 + r * 0.1)
    hinge = (c[0], c[1] - r * 0.95)
    yy, xx = np.mgrid[0:s2, 0:s2].astype(np.float32)
    ang = np.degrees(np.arctan2(yy - hinge[1], xx - hinge[0]))
    dist = np.hypot(yy - hinge[1], xx - hinge[0])
    ribs = 0.5 + 0.5 * np.cos(np.radians(ang) * 34.0)
    rings = 0.5 + 0.5 * np.cos(dist / r * 40.0 + rng.uniform(0, 6))
    shade = 0.7 + 0.25 * ribs + 0.08 * rings
    mask = np.zeros((s2, s2), np.float32)
    cv2.ellipse(mask, (int(c[0]), int(c[1])), (int(r), int(r * 0.93)), 0, 0, 360, 1.0, -1,
                cv2.LINE_AA)
    ear = np.array([[hinge[0] - r * 0.55, hinge[1] - r * 0.05], [hinge[0] + r * 0.55,
                    hinge[1] - r * 0.05], [hinge[0] + r * 0.3, hinge[1] + r * 0.35],
                    [hinge[0] - r * 0.3, hinge[1] + r * 0.35]], np.int32)
    cv2.fillPoly(mask, [ear], 1.0, cv2.LINE_AA)
    band = np.clip(1.0 - np.abs(np.sin(np.radians(ang) * 3.0 + 1.0)) * 0.15, 0.85, 1.0)
    spots = cv2.GaussianBlur(rng.random((s2, s2), dtype=np.float32), (0, 0), 6.0)
    col = base[None, None, :] * (shade * band * (0.85 + 0.5 * (spots - 0.5)))[..., None]
    sand = (rng.random((s2, s2)) < 0.01).astype(np.float32)  # grains caught on the shell
    col = col * (1 - sand[..., None]) + sand[..., None] * np.array([150, 175, 195], np.float32)
    out = []
    for opened in (False, True):
        cimg = col.copy()
        if opened:  # the gape: dark gap, pale mantle fringe, a row of tiny blue eyes
            ctr = (int(c[0]), int(c[1]))
            cv2.ellipse(cimg, ctr, (int(r * 0.97), int(r * 0.9)), 0, 25, 155, (25, 30, 35),
                        int(r * 0.12), cv2.LINE_AA)
            cv2.ellipse(cimg, ctr, (int(r * 0.9), int(r * 0.83)), 0, 30, 150, (150, 170, 185),
                        int(r * 0.04), cv2.LINE_AA)
            for k in range(14):
                a = math.radians(32 + k * 8.5)
                e = (int(c[0] + r * 0.95 * math.cos(a)), int(c[1] + r * 0.88 * math.sin(a)))
                cv2.circle(cimg, e, max(int(r * 0.025), 1), (190, 120, 40), -1, cv2.LINE_AA)
        shadow = _shadow((s2, s2), mask, 0.4, r * 0.08)
        out.append(_finish(cimg, mask, shadow, side, size_m))
    return out[0], out[1]


# --- boulders and tags ----------------------------------------------------------


def boulder(rng: np.random.Generator, diameter_m: float, side: int = 192) -> Sprite:
    """A rounded boulder with speckle and patches of encrusting algae."""
    s2 = side * 2
    r = s2 / 1.6 / 2
    n = 48
    th = np.linspace(0, 2 * math.pi, n, endpoint=False)
    wob = np.ones(n)
    for k in (2, 3, 5):
        wob += rng.uniform(0.03, 0.1) * np.sin(k * th + rng.uniform(0, 6))
    pts = np.stack([s2 / 2 + r * wob * np.cos(th), s2 / 2 + r * wob * np.sin(th)], 1)
    mask = np.zeros((s2, s2), np.float32)
    cv2.fillPoly(mask, [pts.astype(np.int32)], 1.0, cv2.LINE_AA)
    dist = cv2.distanceTransform((mask > 0.5).astype(np.uint8), cv2.DIST_L2, 5)
    dome = np.sqrt(np.clip(dist / (dist.max() + 1e-6), 0, 1))
    gx = cv2.Sobel(dome, cv2.CV_32F, 1, 0, ksize=5)
    gy = cv2.Sobel(dome, cv2.CV_32F, 0, 1, ksize=5)
    light = np.clip(0.8 + (-0.2 * gx + 0.6 * gy) * 0.02, 0.35, 1.2) * (0.55 + 0.45 * dome)
    grey = rng.uniform(70, 140)
    base = np.array([grey * 0.95, grey, grey * 1.05], np.float32)
    speck = cv2.GaussianBlur(rng.random((s2, s2), dtype=np.float32), (0, 0), 1.2)
    col = base[None, None, :] * (light * (0.75 + 0.5 * speck))[..., None]
    crust = cv2.GaussianBlur(rng.random((s2 // 16, s2 // 16), dtype=np.float32), (0, 0), 1.0)
    crust = cv2.resize(crust, (s2, s2), interpolation=cv2.INTER_CUBIC)
    patch = np.clip((crust - 0.55) * 8, 0, 1)[..., None] * 0.8
    tint = np.array(rng.choice([[120, 110, 200], [60, 110, 80]]), np.float32)  # coralline, green
    col = col * (1 - patch) + patch * tint * light[..., None]
    shadow = _shadow((s2, s2), mask, 0.6, r * 0.12)
    return _finish(col, mask, shadow, side, diameter_m * 1.6)


def tag_sprite(tag_id: int, black_m: float, side: int = 160) -> Sprite:
    """An AprilTag 36h11 printed on a white plate; the black square is black_m wide.

    The 36h11 marker is 8 cells wide inside its black border, with a one-cell white
    border around the plate (10 cells in all).
    """
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    marker = cv2.aruco.generateImageMarker(d, tag_id, 80)
    plate = cv2.copyMakeBorder(marker, 10, 10, 10, 10, cv2.BORDER_CONSTANT, value=255)
    img = cv2.resize(plate, (side, side), interpolation=cv2.INTER_NEAREST).astype(np.float32)
    col = np.dstack([img * 0.92, img * 0.95, img * 0.97])
    body = np.ones((side, side), np.float32)
    rgba = np.dstack([col, body])
    return Sprite(rgba=rgba, body=body, size_m=black_m * 10.0 / 8.0)
