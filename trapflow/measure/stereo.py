"""Range, 3-D position and length of one box in the left image of a rectified stereo pair.

Pure functions over numpy arrays: a rectified grey pair, the rig and a box in, a Measured
or an Unmeasured (with its reason) out. No answer rather than a wrong one.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import msgspec
import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.measure.floor import FloorPlane, fit_floor, floor_slopes

Reason = Literal["bad_box", "out_of_view", "textureless", "ambiguous", "low_score"]
Matcher = Literal["ncc", "sgbm"]
LengthMethod = Literal["box", "endpoints"]
Box = tuple[float, float, float, float]
RESIDUAL_CORRELATION = 2.0
PEAK_SIDE_PX = 3


class MeasureParams(msgspec.Struct, frozen=True, kw_only=True):
    """Search limits, acceptance thresholds and error terms of a measurement."""

    min_range_m: float = 0.3
    """Nearest range searched (sets the largest disparity, so the search band's width)."""
    max_range_m: float = 10.0
    """Farthest range searched (the smallest disparity)."""
    min_texture: float = 5.0
    """Grey-level standard deviation below which a patch is textureless (sensor noise
    alone gives about 2.5 on the synthetic default)."""
    min_score: float = 0.5
    """Normalised cross-correlation below which the match is refused (low_score)."""
    clipped_min_score: float = 0.75
    """The same where the search was cut short by the right image's edge."""
    ambiguity_margin: float = 0.04
    """A second correlation peak within this of the best one makes the match ambiguous."""
    coarse_side_px: int = 32
    """Patches larger than this are searched reduced first, then refined at full size."""
    box_sd_px: float = 0.7
    """Standard deviation of a box edge, pixels (a truth box is whole pixels: 0.3)."""
    disparity_sd_floor_px: float = 0.1
    """Disparity error that no fit removes (interpolation, rectification)."""
    shape_rel_sd: float = 0.03
    """Relative sd of how far a box's extent is from the body's longest chord, for a box
    much longer than wide (the body can only lie along it)."""
    diagonal_rel_sd: float = 0.05
    """Added to shape_rel_sd per unit of the box's diagonal excess (diagonal / longer centre
    line - 1): a squarer box may hold a body lying along its diagonal, longer than either
    centre line (development seeds: crabs within 2 sd 0.87 with a flat 0.04, 0.92 so)."""
    relief_rel_sd: float = 0.05
    """Range sd from what a box holds besides the body's centre (floor between legs, the
    body's own height), as a fraction of the measured length."""
    scale_rel_sd: float = 0.0
    """Relative sd of the calibration's focal length x baseline (0: known exactly)."""
    floor_slope_sd: float = 0.004
    """Sd of a body's disparity slope (px per px) about the floor plane's: the floor's relief
    under it and how it lies."""


class Measured(msgspec.Struct, frozen=True, kw_only=True):
    """What the rig measured of one box (camera frame: x right, y down, z forward; metres)."""

    disparity_px: float
    disparity_sd_px: float
    range_m: float  # from the left camera's centre to the box centre's 3-D point
    range_sd_m: float
    xyz: tuple[float, float, float]
    length_m: float
    length_sd_m: float
    length_method: LengthMethod
    matcher: Matcher
    score: float  # the match's quality: peak correlation, or SGBM's valid fraction


class Unmeasured(msgspec.Struct, frozen=True, kw_only=True):
    """No numbers: why the box could not be measured."""

    reason: Reason
    detail: str


Measurement = Measured | Unmeasured


class Surface(msgspec.Struct, frozen=True, kw_only=True):
    """Disparity over a box as a plane d = c + a (u - uc) + b (v - vc), with its covariance.

    `planar` is False when only c was measured (a = b = 0): lengths then use the box method.
    """

    uc: float
    vc: float
    c: float
    a: float
    b: float
    cov: tuple[float, ...]  # 3x3 row major over (c, a, b)
    planar: bool
    score: float

    def at(self, u: float, v: float) -> float:
        """The plane's disparity at pixel (u, v)."""
        return self.c + self.a * (u - self.uc) + self.b * (v - self.vc)


def disparity_limits(rig: StereoRig, params: MeasureParams) -> tuple[int, int]:
    """The smallest and largest disparity searched, whole pixels."""
    fb = rig.fx * rig.baseline_m
    return max(int(math.floor(fb / params.max_range_m)), 0), int(math.ceil(fb / params.min_range_m))


def triangulate(rig: StereoRig, u: float, v: float, d: float) -> np.ndarray:
    """The camera-frame point (m) of left pixel (u, v) at disparity d."""
    z = rig.fx * rig.baseline_m / d
    return np.array([(u - rig.cx) * z / rig.fx, (v - rig.cy) * z / rig.fy, z])


def pair_floor(left: np.ndarray, right: np.ndarray, rig: StereoRig,
               params: MeasureParams | None = None) -> FloorPlane | None:
    """The floor's disparity plane of a rectified grey pair (once per pair, for all its
    boxes), or None where no plane holds the pair's matches."""
    return fit_floor(left, right, rig, disparity_limits(rig, params or MeasureParams()))


def measure(left: np.ndarray, right: np.ndarray, rig: StereoRig, box: Box,
            params: MeasureParams | None = None, matcher: Matcher = "ncc",
            floor: FloorPlane | None = None) -> Measurement:
    """Measure the box's content: range, position and length with their uncertainties.

    `left`, `right`: the rectified pair, grey uint8, the rig's size. `box`: x1 y1 x2 y2 in
    left-image pixels (x2, y2 exclusive, as detectors and the synthetic truth give them).
    `floor` (pair_floor's): the slant a body lying on the floor shares, combined with the
    box's own.
    """
    p = params or MeasureParams()
    ints = _clip_box(box, left.shape[1], left.shape[0])
    if ints is None:
        return Unmeasured(reason="bad_box", detail=f"box {box} has no pixels in the image")
    found = (match_ncc(left, right, ints, rig, p) if matcher == "ncc"
             else match_sgbm(left, right, ints, rig, p))
    if isinstance(found, Unmeasured):
        return found
    if floor is not None:
        found = _on_floor(found, floor, p)
    return _result(found, box, rig, p, matcher)


def _on_floor(s: Surface, floor: FloorPlane, params: MeasureParams) -> Surface:
    """The box's disparity slopes combined with the floor's (scaled to the box's disparity),
    each weighted by its inverse variance; a box too small for slopes of its own takes the
    floor's."""
    slopes = floor_slopes(floor, s.uc, s.vc, s.c)
    if slopes is None:
        return s
    cov = np.array(s.cov).reshape(3, 3)
    prior = params.floor_slope_sd ** 2
    coef = [s.c, *slopes]
    out = np.zeros((3, 3))
    out[0, 0] = cov[0, 0]
    for i, own in ((1, s.a), (2, s.b)):
        var = cov[i, i]
        if s.planar and var > 0:
            coef[i] = (own / var + coef[i] / prior) / (1 / var + 1 / prior)
            out[i, i] = 1 / (1 / var + 1 / prior)
        else:
            out[i, i] = prior
    return Surface(uc=s.uc, vc=s.vc, c=s.c, a=float(coef[1]), b=float(coef[2]),
                   cov=tuple(float(v) for v in out.ravel()), planar=True, score=s.score)


# --- matchers ---------------------------------------------------------------------------


def match_ncc(left: np.ndarray, right: np.ndarray, box: tuple[int, int, int, int],
              rig: StereoRig, params: MeasureParams) -> Surface | Unmeasured:
    """The box's patch slid along its rows of the right image (normalised cross-correlation),
    then the box's cells matched near that disparity and fitted with a plane."""
    x1, y1, x2, y2 = box
    patch = left[y1:y2, x1:x2]
    texture = float(patch.std())
    if texture < params.min_texture:
        return Unmeasured(reason="textureless",
                          detail=f"patch grey-level sd {texture:.1f} < {params.min_texture}")
    d_lo, d_hi = disparity_limits(rig, params)
    hi = min(d_hi, x1)  # the patch's left edge must stay inside the right image
    if hi < d_lo + 1:
        return Unmeasured(reason="out_of_view",
                          detail=f"box at x {x1} leaves the right image at any disparity "
                                 f">= {d_lo}")
    curve, k = _coarse_curve(left, right, box, d_lo, hi, params.coarse_side_px)
    side = max(PEAK_SIDE_PX, 2 * k + 1)  # a reduced patch's peak is k times as wide
    j = int(np.argmax(curve))
    clipped = hi < d_hi
    # A peak must rise above the curve `side` px to each side inside the search: a flat curve cut
    # by the image edge once gave a 5 m range for a crab at 1.3 m.
    top = float(curve[j]) - params.ambiguity_margin
    if j < side or curve[j - side] >= top:
        return Unmeasured(reason="out_of_view" if clipped else "low_score",
                          detail=f"no peak below disparity {hi}"
                                 + (f" (the right image's edge for x {x1})" if clipped else ""))
    if j + side >= curve.size or curve[j + side] >= top:
        return Unmeasured(reason="low_score", detail=f"no peak above disparity {d_lo}")
    d_best, score, fine = _refine(left, right, box, hi - j, 3, d_lo, hi)
    # A search cut by the image edge may have lost the true match (the animal half out of
    # the right image) and then finds a weak false one: only a strong match is believed.
    need = max(params.min_score, params.clipped_min_score) if clipped else params.min_score
    if score < need:
        return Unmeasured(reason="out_of_view" if clipped else "low_score",
                          detail=f"peak correlation {score:.2f} < {need}"
                                 + (f"; search cut at the image edge ({hi} px)" if clipped else ""))
    second = _second_peak(curve, j)
    if second > float(curve[j]) - params.ambiguity_margin:  # both peaks from one curve
        return Unmeasured(reason="ambiguous",
                          detail=f"second peak {second:.2f} within {params.ambiguity_margin} "
                                 f"of the best {float(curve[j]):.2f}")
    sd0 = _shift_sd(patch, fine, score, params)
    return _cell_plane(left, right, box, d_best, sd0, score, (d_lo, hi), params)


def _coarse_curve(left: np.ndarray, right: np.ndarray, box: tuple[int, int, int, int],
                  d_lo: int, d_hi: int, side: int) -> tuple[np.ndarray, int]:
    """Correlation per whole-pixel disparity d_hi, d_hi - 1, ..., d_lo (index j = d_hi - d),
    and the factor k the patch was reduced by.

    A large patch is searched reduced by an integer factor (cost grows with its area);
    the reduced curve is stretched back to whole pixels for the peak tests.
    """
    x1, y1, x2, y2 = box
    k = max(1, int(math.ceil(max(x2 - x1, y2 - y1) / side)))
    band = right[y1:y2, x1 - d_hi:x2 - d_lo]
    patch = left[y1:y2, x1:x2]
    if k > 1:
        size = (max((x2 - x1) // k, 2), max((y2 - y1) // k, 2))
        patch = cv2.resize(patch, size, interpolation=cv2.INTER_AREA)
        band = cv2.resize(band, (max(band.shape[1] // k, size[0]), size[1]),
                          interpolation=cv2.INTER_AREA)
    res = cv2.matchTemplate(band, patch, cv2.TM_CCOEFF_NORMED)
    curve = np.nan_to_num(res.max(axis=0), nan=-1.0)
    if k > 1:
        xs = np.arange(d_hi - d_lo + 1) / k
        curve = np.interp(xs, np.arange(curve.size), curve)
    out: np.ndarray = curve
    return out, k


def _refine(left: np.ndarray, right: np.ndarray, box: tuple[int, int, int, int], d0: float,
            radius: int, d_lo: int, d_hi: int) -> tuple[float, float, np.ndarray]:
    """Full-size correlation within radius of d0: sub-pixel disparity (parabola through the
    peak and its neighbours), the peak score, and the curve itself."""
    x1, y1, x2, y2 = box
    top = min(int(round(d0)) + radius, d_hi)
    bottom = max(int(round(d0)) - radius, d_lo)
    band = right[y1:y2, x1 - top:x2 - bottom]
    res = cv2.matchTemplate(band, left[y1:y2, x1:x2], cv2.TM_CCOEFF_NORMED)
    curve = np.nan_to_num(res[0], nan=-1.0)
    j = int(np.argmax(curve))
    score = float(curve[j])
    offset = 0.0
    if 0 < j < curve.size - 1:
        lo_, mid, hi_ = float(curve[j - 1]), score, float(curve[j + 1])
        den = lo_ - 2 * mid + hi_
        if den < 0:
            offset = 0.5 * (lo_ - hi_) / den
    # index j is disparity top - j; a positive offset moves to a larger index
    return top - (j + offset), score, curve


def _second_peak(curve: np.ndarray, j: int) -> float:
    """The highest local maximum of the curve away from the best peak's own slopes."""
    n = curve.size
    lo = j
    while lo > 0 and curve[lo - 1] <= curve[lo]:
        lo -= 1
    hi = j
    while hi < n - 1 and curve[hi + 1] <= curve[hi]:
        hi += 1
    rest = np.concatenate([curve[:lo], curve[hi + 1:]])
    return float(rest.max()) if rest.size else -1.0


def _shift_sd(patch: np.ndarray, curve: np.ndarray, score: float,
              params: MeasureParams) -> float:
    """Standard deviation of a patch's matched shift: the residual that the correlation
    leaves (2 var (1 - rho) per pixel) over the patch's horizontal gradient energy, as for a
    least-squares shift; floored."""
    f = patch.astype(np.float32)
    gx = (f[:, 2:] - f[:, :-2]) / 2.0
    energy = float((gx * gx).sum())
    var = 2.0 * float(f.var()) * max(1.0 - score, 1e-3)
    # x RESIDUAL_CORRELATION: rendered and interpolated images have residuals correlated
    # over about 2 x 2 pixels, a quarter as many independent samples as pixels.
    sd = RESIDUAL_CORRELATION * math.sqrt(var / max(energy, 1e-6))
    return math.hypot(sd, params.disparity_sd_floor_px)


def _cell_plane(left: np.ndarray, right: np.ndarray, box: tuple[int, int, int, int],
                d0: float, sd0: float, score: float, limits: tuple[int, int],
                params: MeasureParams) -> Surface:
    """Match a grid of the box's cells near d0 and fit the disparity plane through them.

    Animals lie on a floor seen at a slant: disparity changes across a box by several
    pixels, which moves the two ends of a length apart in depth. Falls back to a flat
    surface at d0 when too few cells match.
    """
    x1, y1, x2, y2 = box
    w, h = x2 - x1, y2 - y1
    nx = max(1, min(3, w // 12))
    ny = max(1, min(3, h // 12))
    uc, vc = (x1 + x2 - 1) / 2.0, (y1 + y2 - 1) / 2.0
    rows: list[tuple[float, float, float, float]] = []
    if nx * ny >= 3:
        xs = np.linspace(x1, x2, nx + 1).round().astype(int)
        ys = np.linspace(y1, y2, ny + 1).round().astype(int)
        for i in range(nx):
            for k in range(ny):
                cell = (int(xs[i]), int(ys[k]), int(xs[i + 1]), int(ys[k + 1]))
                cp = left[cell[1]:cell[3], cell[0]:cell[2]]
                if float(cp.std()) < params.min_texture:
                    continue
                d, s, curve = _refine(left, right, cell, d0, 4, limits[0], limits[1])
                edge = abs(d - d0) > 3.5  # pinned at the window's edge: no real peak
                if s < params.min_score or edge:
                    continue
                rows.append(((cell[0] + cell[2] - 1) / 2.0, (cell[1] + cell[3] - 1) / 2.0, d,
                             _shift_sd(cp, curve, s, params)))
    flat = Surface(uc=uc, vc=vc, c=d0, a=0.0, b=0.0,
                   cov=(sd0 * sd0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0), planar=False,
                   score=score)
    if len(rows) < 3:
        return flat
    pts = np.array(rows)
    if np.ptp(pts[:, 0]) == 0 or np.ptp(pts[:, 1]) == 0:
        return flat
    fit = _plane_fit(pts, uc, vc)
    if fit is None:
        return flat
    coef, cov = _significant(*fit)
    return Surface(uc=uc, vc=vc, c=float(coef[0]), a=float(coef[1]), b=float(coef[2]),
                   cov=tuple(float(v) for v in cov.ravel()), planar=True, score=score)


def _significant(coef: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slopes within 2 sd of zero set to zero: on small boxes a noisy slope costs more
    length accuracy (measured: 3.9 % against 2.1 % on scallops) than it corrects."""
    coef, cov = coef.copy(), cov.copy()
    for i in (1, 2):
        if abs(coef[i]) < 2.0 * math.sqrt(max(cov[i, i], 0.0)):
            coef[i] = 0.0
    return coef, cov


def _plane_fit(pts: np.ndarray, uc: float, vc: float
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """Weighted least squares of d = c + a du + b dv over (u, v, d, sd) rows; one outlier
    (beyond 3 sd of the fit) dropped and the fit redone. The covariance is scaled up by the
    residual's reduced chi-square when the points scatter more than their sds say."""
    for _ in range(2):
        a = np.column_stack([np.ones(len(pts)), pts[:, 0] - uc, pts[:, 1] - vc])
        wts = 1.0 / pts[:, 3]
        aw = a * wts[:, None]
        normal = aw.T @ aw
        if np.linalg.cond(normal) > 1e8:
            return None
        cov = np.linalg.inv(normal)
        coef = cov @ (aw.T @ (pts[:, 2] * wts))
        res = (pts[:, 2] - a @ coef) * wts
        dof = len(pts) - 3
        if dof > 0:
            cov = cov * max(1.0, float((res * res).sum()) / dof)
        worst = int(np.argmax(np.abs(res)))
        if abs(res[worst]) <= 3.0 or len(pts) <= 4:
            return coef, cov
        pts = np.delete(pts, worst, axis=0)
    return coef, cov


def match_sgbm(left: np.ndarray, right: np.ndarray, box: tuple[int, int, int, int],
               rig: StereoRig, params: MeasureParams) -> Surface | Unmeasured:
    """Semi-global matching on a band around the box (extended left by the largest
    disparity), the box's central half summarised by its median and a fitted plane."""
    x1, y1, x2, y2 = box
    texture = float(left[y1:y2, x1:x2].std())
    if texture < params.min_texture:
        return Unmeasured(reason="textureless",
                          detail=f"patch grey-level sd {texture:.1f} < {params.min_texture}")
    d_lo, d_hi = disparity_limits(rig, params)
    num = int(math.ceil((d_hi - d_lo) / 16.0)) * 16
    block, pad = 5, 4
    bx0 = x1 - num - d_lo - pad
    if bx0 < 0:
        return Unmeasured(reason="out_of_view",
                          detail=f"box at x {x1} leaves the right image within the search")
    by0, by1 = max(y1 - pad, 0), min(y2 + pad, left.shape[0])
    bx1 = min(x2 + pad, left.shape[1])
    sgbm = cv2.StereoSGBM.create(minDisparity=d_lo, numDisparities=num, blockSize=block,
                                 P1=8 * block * block, P2=32 * block * block,
                                 uniquenessRatio=10, disp12MaxDiff=1,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disp = sgbm.compute(left[by0:by1, bx0:bx1], right[by0:by1, bx0:bx1]).astype(np.float32)
    disp /= 16.0
    inner = disp[y1 - by0:y2 - by0, x1 - bx0:x2 - bx0]
    h, w = inner.shape
    centre = inner[h // 4:h - h // 4, w // 4:w - w // 4]
    good = centre[centre >= d_lo]
    frac = float(good.size) / max(centre.size, 1)
    if frac < 0.3:
        return Unmeasured(reason="low_score", detail=f"{frac:.0%} of the centre matched")
    med = float(np.median(good))
    mad = 1.4826 * float(np.median(np.abs(good - med)))
    sd0 = math.hypot(mad / math.sqrt(good.size / 9.0), params.disparity_sd_floor_px)
    uc, vc = (x1 + x2 - 1) / 2.0, (y1 + y2 - 1) / 2.0
    vs, us = np.nonzero(inner >= d_lo)
    ds = inner[vs, us]
    keep = np.abs(ds - med) < max(4.0 * mad, 2.0)
    flat = Surface(uc=uc, vc=vc, c=med, a=0.0, b=0.0, cov=(sd0 * sd0,) + (0.0,) * 8,
                   planar=False, score=frac)
    if keep.sum() < 20:
        return flat
    # Neighbouring pixels of a block matcher are far from independent: one sd per
    # block area, not per pixel.
    pts = np.column_stack([us[keep] + x1, vs[keep] + y1, ds[keep],
                           np.full(int(keep.sum()), max(mad, 0.25) * block)])
    fit = _plane_fit(pts, uc, vc)
    if fit is None:
        return flat
    coef, cov = fit
    return Surface(uc=uc, vc=vc, c=med, a=float(coef[1]), b=float(coef[2]),
                   cov=(sd0 * sd0, 0.0, 0.0, 0.0) + tuple(float(v) for v in cov.ravel()[4:]),
                   planar=True, score=frac)


# --- from disparity to metres -------------------------------------------------------------


def _result(s: Surface, box: Box, rig: StereoRig, params: MeasureParams,
            matcher: Matcher) -> Measured:
    x1, y1, x2, y2 = box
    uc, vc = (x1 + x2 - 1) / 2.0, (y1 + y2 - 1) / 2.0
    cov = np.array(s.cov).reshape(3, 3)
    d = s.at(uc, vc)
    gd = np.array([1.0, uc - s.uc, vc - s.vc])
    sd_d = math.sqrt(float(gd @ cov @ gd))
    xyz = triangulate(rig, uc, vc, d)
    rng = float(np.linalg.norm(xyz))
    # range is proportional to 1/d along the centre's ray: sd_R = R sd_d / d
    length, sd_l = _length(s, (x1 - 0.5, y1 - 0.5, x2 - 0.5, y2 - 0.5), rig, cov, params)
    sd_r = math.hypot(rng * sd_d / d, rng * params.scale_rel_sd, length * params.relief_rel_sd)
    return Measured(disparity_px=round(d, 3), disparity_sd_px=round(sd_d, 3),
                    range_m=round(rng, 4), range_sd_m=round(sd_r, 4),
                    xyz=(round(float(xyz[0]), 4), round(float(xyz[1]), 4),
                         round(float(xyz[2]), 4)),
                    length_m=round(length, 4), length_sd_m=round(sd_l, 4),
                    length_method="endpoints" if s.planar else "box", matcher=matcher,
                    score=round(s.score, 3))


def _length(s: Surface, edges: Box, rig: StereoRig, cov: np.ndarray,
            params: MeasureParams) -> tuple[float, float]:
    """The longer of the box's two centre lines in 3-D, end points at the plane's disparity,
    and its sd (box edges, plane, shape and calibration terms)."""
    x1, y1, x2, y2 = edges
    uc, vc = (x1 + x2) / 2.0, (y1 + y2) / 2.0
    lines = ((x1, vc, x2, vc), (uc, y1, uc, y2))

    def chord(q: np.ndarray, plane: np.ndarray) -> float:
        c, a, b = plane
        ends = [triangulate(rig, float(q[i]), float(q[i + 1]),
                            float(c + a * (q[i] - s.uc) + b * (q[i + 1] - s.vc)))
                for i in (0, 2)]
        return float(np.linalg.norm(ends[0] - ends[1]))

    plane = np.array([s.c, s.a, s.b])
    best = max((np.array(line) for line in lines), key=lambda q: chord(q, plane))
    length = chord(best, plane)
    diagonal = max(chord(np.array(q), plane) for q in ((x1, y1, x2, y2), (x1, y2, x2, y1)))
    shape = params.shape_rel_sd + params.diagonal_rel_sd * max(diagonal / length - 1.0, 0.0)
    var = 0.0
    for i in range(4):  # the end points' pixel coordinates: the box's own error
        step = np.zeros(4)
        step[i] = 0.25
        g = (chord(best + step, plane) - chord(best - step, plane)) / 0.5
        var += (g * params.box_sd_px) ** 2
    grad = np.zeros(3)
    for i in range(3):
        step = np.zeros(3)
        step[i] = 1e-3 if i else 0.05
        grad[i] = (chord(best, plane + step) - chord(best, plane - step)) / (2 * step[i])
    var += float(grad @ cov @ grad)
    var += (length * shape) ** 2 + (length * params.scale_rel_sd) ** 2
    return length, math.sqrt(var)


def _clip_box(box: Box, width: int, height: int) -> tuple[int, int, int, int] | None:
    """The box as whole pixels inside the image, or None when it has fewer than 4 x 4."""
    x1 = max(int(math.floor(box[0])), 0)
    y1 = max(int(math.floor(box[1])), 0)
    x2 = min(int(math.ceil(box[2])), width)
    y2 = min(int(math.ceil(box[3])), height)
    if x2 - x1 < 4 or y2 - y1 < 4:
        return None
    return x1, y1, x2, y2
