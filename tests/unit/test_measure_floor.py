"""The floor's disparity plane of a pair, against the plane the synthetic world's floor lies on
(its mean height z = 0 seen from the rig's true pose), and what it gives a box's length."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from trapflow.calibration.camera import StereoRig
from trapflow.measure.floor import FloorPlane, floor_slopes
from trapflow.measure.stereo import Measured, measure, pair_floor
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World

RIG = StereoRig.from_fov(640, 360, 70.0, 0.12)
FB = RIG.fx * RIG.baseline_m


def _true_plane(world: World, t_s: float) -> tuple[float, float, float]:
    """(g, a, b) of the world's mean floor: the plane n.X = -h in the camera frame (n the
    floor's up in camera axes, h the camera's height) has disparity fB (n.ray) / -h."""
    pose = world.traj.floor_pose(t_s)
    n = pose[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    h = float(pose[2, 3])
    return FB * n[2] / -h, FB * n[0] / (RIG.fx * -h), FB * n[1] / (RIG.fy * -h)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("moving", [False, True])
def test_the_floor_plane_is_the_worlds(moving: bool) -> None:
    world = World(RIG, seed=5, moving=moving, rate_hz=10.0,
                  options=SynthOptions(density=2.0, empty_fraction=0.0))
    left, right, _ = world.render(50)
    floor = pair_floor(cv2.cvtColor(left, cv2.COLOR_BGR2GRAY),
                       cv2.cvtColor(right, cv2.COLOR_BGR2GRAY), RIG)
    assert floor is not None
    g, a, b = _true_plane(world, 5.0)
    # measured on seed 5: g within 0.3 %, b within 3 % (the floor's relief), a within 0.002
    assert floor.g == pytest.approx(g, rel=0.01)
    assert floor.b == pytest.approx(b, rel=0.08)
    assert floor.a == pytest.approx(a, abs=0.004)
    assert floor.share >= 0.4


@pytest.mark.parametrize(("left", "why"), [
    (np.full((360, 640), 90, np.uint8), "textureless: nothing matches"),
    (np.random.default_rng(1).integers(0, 255, (40, 60), dtype=np.uint8),
     "too small for the search"),
])
def test_no_floor(left: np.ndarray, why: str) -> None:
    rig = RIG if left.shape == (360, 640) else StereoRig.from_fov(60, 40, 70.0, 0.12)
    assert pair_floor(left, left.copy(), rig) is None, why


def test_a_body_on_the_floor_takes_its_slope_scaled() -> None:
    """A body parallel to the floor, 10 % nearer, has 10/9 the floor's disparity and slopes."""
    floor = FloorPlane(g=40.0, a=0.01, b=0.1, cx=319.5, cy=179.5, spread_px=0.3, share=0.6)
    d = floor.at(400.0, 250.0) / 0.9
    slopes = floor_slopes(floor, 400.0, 250.0, d)
    assert slopes is not None
    assert slopes[0] == pytest.approx(0.01 / 0.9) and slopes[1] == pytest.approx(0.1 / 0.9)
    # behind the camera (no disparity): no slope
    assert floor_slopes(FloorPlane(g=-1.0, a=0.0, b=0.0, cx=0, cy=0, spread_px=0, share=1),
                        0.0, 0.0, 5.0) is None


@pytest.mark.timeout(60)
def test_small_boxes_get_end_points_on_the_floors_slant() -> None:
    """Regression: a box too small for a plane of its own was measured flat (method `box`),
    its far end as near as its centre: lengths 2-3 % short at 2 m. With the floor's plane it
    gets end points, within 3 sd of the truth."""
    world = World(RIG, seed=5, moving=False, rate_hz=10.0,
                  options=SynthOptions(density=2.0, empty_fraction=0.0))
    left, right, truth = world.render(50)
    gl, gr = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY), cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)
    floor = pair_floor(gl, gr, RIG)
    small = 0
    for o in truth.objects:
        if o.label == "tag" or o.occluded > 0.1:
            continue
        alone = measure(gl, gr, RIG, o.box)
        m = measure(gl, gr, RIG, o.box, floor=floor)
        assert isinstance(alone, Measured) and isinstance(m, Measured)
        assert m.length_method == "endpoints"
        assert abs(m.length_m - o.length_m) <= 3 * m.length_sd_m
        assert m.range_m == pytest.approx(math.dist(o.xyz or (0, 0, 0), (0, 0, 0)), rel=0.02)
        small += alone.length_method == "box"
    assert small >= 1, "no box too small for its own plane: the regression is not exercised"
