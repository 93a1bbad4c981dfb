"""Stereo measurement of a box on rendered synthetic pairs (known depth and length), and the
reason codes where it must refuse: a textureless patch, a box leaving the right image."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from trapflow.calibration.camera import StereoRig
from trapflow.measure.stereo import Measured, MeasureParams, Unmeasured, measure, triangulate
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World

RIG = StereoRig.from_fov(640, 360, 70.0, 0.12)


@pytest.fixture(scope="module")
def rendered() -> tuple[np.ndarray, np.ndarray, list[tuple[tuple[float, ...], float, float]]]:
    """A static synthetic pair with animals: grey images, (box, range, length) per animal."""
    world = World(RIG, seed=5, moving=False, rate_hz=10.0,
                  options=SynthOptions(density=2.0, empty_fraction=0.0))
    left, right, truth = world.render(50)
    animals = [(o.box, math.dist(o.xyz, (0, 0, 0)), o.length_m) for o in truth.objects
               if o.label != "tag" and o.xyz is not None and o.occluded < 0.1]
    assert len(animals) >= 4
    return (cv2.cvtColor(left, cv2.COLOR_BGR2GRAY), cv2.cvtColor(right, cv2.COLOR_BGR2GRAY),
            animals)


def test_triangulate_inverts_the_projection() -> None:
    p = triangulate(RIG, 400.0, 100.0, RIG.fx * RIG.baseline_m / 2.0)
    assert p[2] == pytest.approx(2.0)
    assert RIG.fx * p[0] / p[2] + RIG.cx == pytest.approx(400.0)
    assert RIG.fy * p[1] / p[2] + RIG.cy == pytest.approx(100.0)


@pytest.mark.timeout(60)
def test_animals_measured_within_percent_and_their_sd(
        rendered: tuple[np.ndarray, np.ndarray, list[tuple[tuple[float, ...], float, float]]]
) -> None:
    """Truth boxes of rendered scallops: range within 2 % and 3 sd, length within 3 sd."""
    left, right, animals = rendered
    for box, rng, length in animals:
        m = measure(left, right, RIG, (box[0], box[1], box[2], box[3]))
        assert isinstance(m, Measured), m
        assert m.range_m == pytest.approx(rng, rel=0.02)
        assert abs(m.range_m - rng) <= 3 * m.range_sd_m
        assert abs(m.length_m - length) <= 3 * m.length_sd_m
        assert m.xyz[2] == pytest.approx(RIG.fx * RIG.baseline_m / m.disparity_px, rel=1e-3)


@pytest.mark.timeout(60)
def test_sgbm_matcher_agrees_with_correlation(
        rendered: tuple[np.ndarray, np.ndarray, list[tuple[tuple[float, ...], float, float]]]
) -> None:
    left, right, animals = rendered
    box = animals[0][0]
    a = measure(left, right, RIG, (box[0], box[1], box[2], box[3]), matcher="ncc")
    b = measure(left, right, RIG, (box[0], box[1], box[2], box[3]), matcher="sgbm")
    assert isinstance(a, Measured) and isinstance(b, Measured)
    assert b.matcher == "sgbm"
    assert b.disparity_px == pytest.approx(a.disparity_px, abs=1.0)


def shifted_pair(disparity: int) -> tuple[np.ndarray, np.ndarray]:
    """A random-texture plane at one disparity: right = left moved left by `disparity`."""
    rng = np.random.default_rng(3)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (360, 640 + disparity), dtype=np.uint8),
                           (0, 0), 1.2)
    return np.ascontiguousarray(tex[:, :640]), np.ascontiguousarray(tex[:, disparity:])


@pytest.mark.parametrize(
    ("box", "reason"),
    [
        # a plain grey square painted over the texture: nothing to match
        ((300, 150, 340, 190), "textureless"),
        # 10 px from the left edge at disparity 40: the match lies outside the right image
        ((10, 150, 60, 190), "out_of_view"),
        # no pixels inside the image
        ((700, 10, 720, 30), "bad_box"),
    ],
)
def test_reason_codes(box: tuple[float, float, float, float], reason: str) -> None:
    left, right = shifted_pair(40)
    left[150:190, 300:340] = 120
    m = measure(left, right, RIG, box)
    assert isinstance(m, Unmeasured) and m.reason == reason, m


def test_plane_disparity_recovered_exactly() -> None:
    """A fronto-parallel random texture at disparity 40: 40 px, range fB/40, within 0.1 px."""
    left, right = shifted_pair(40)
    m = measure(left, right, RIG, (300.0, 150.0, 360.0, 200.0))
    assert isinstance(m, Measured)
    assert m.disparity_px == pytest.approx(40.0, abs=0.1)
    assert m.xyz[2] == pytest.approx(RIG.fx * RIG.baseline_m / 40.0, rel=0.005)


def test_repeating_texture_is_ambiguous() -> None:
    """Vertical stripes with a 20 px period: every period matches as well as the true one."""
    cols = (127 + 100 * np.sin(np.arange(700) * 2 * np.pi / 20)).astype(np.uint8)
    tex = np.tile(cols, (360, 1))
    left, right = tex[:, :640].copy(), tex[:, 40:680].copy()
    m = measure(left, right, RIG, (300.0, 150.0, 360.0, 200.0))
    assert isinstance(m, Unmeasured) and m.reason == "ambiguous", m


def test_params_reject_nothing_silently() -> None:
    """A box beyond the right image at every searched disparity is out_of_view, not a guess."""
    left, right = shifted_pair(40)
    m = measure(left, right, RIG, (0.0, 150.0, 30.0, 190.0), MeasureParams(max_range_m=2.0))
    assert isinstance(m, Unmeasured) and m.reason == "out_of_view"
