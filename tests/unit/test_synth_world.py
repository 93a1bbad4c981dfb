"""The synthetic world: determinism, truth consistency, stereo geometry, option checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trapflow.calibration.camera import StereoRig
from trapflow.config.image_health import ImageHealthConfig
from trapflow.config.schema import SourceConfig
from trapflow.errors import ConfigError
from trapflow.image_health.measure import measure
from trapflow.image_health.watch import Watch
from trapflow.sources.synthetic import SyntheticSource
from trapflow.synth.geometry import inv_pose
from trapflow.synth.options import SynthOptions, parse_options
from trapflow.synth.render import World

RIG = StereoRig.from_fov(320, 180, 70.0, 0.12)


@pytest.fixture(scope="module")
def static_world() -> World:
    return World(RIG, seed=3, moving=False, rate_hz=15.0, options=SynthOptions(density=2.0,
                                                                                 tags=2))


@pytest.fixture(scope="module")
def moving_world() -> World:
    return World(RIG, seed=5, moving=True, rate_hz=15.0)


def test_same_seed_same_pixels() -> None:
    a = World(RIG, seed=11, moving=False, rate_hz=15.0)
    b = World(RIG, seed=11, moving=False, rate_hz=15.0)
    for i in (0, 37, 120):
        la, ra, ta = a.render(i)
        lb, rb, tb = b.render(i)
        assert np.array_equal(la, lb) and np.array_equal(ra, rb)
        assert ta == tb
    other = World(RIG, seed=12, moving=False, rate_hz=15.0)
    assert not np.array_equal(other.render(0)[0], a.render(0)[0])


def test_images_are_bgr_uint8_of_the_rig_size(static_world: World) -> None:
    left, right, truth = static_world.render(0)
    assert left.shape == right.shape == (180, 320, 3)
    assert left.dtype == right.dtype == np.uint8
    assert truth.seq == -1 and len(truth.pose) == 12
    assert 40 < float(left.mean()) < 200


def test_static_pose_is_identity(static_world: World) -> None:
    for i in (0, 50):
        assert static_world.render(i)[2].pose == (1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0)


def test_animals_come_and_go_with_consistent_labels(static_world: World) -> None:
    labels = set()
    for i in range(0, 1500, 15):
        truth = static_world.render(i)[2]
        labels.add(truth.scene_label)
        for o in truth.objects:
            x1, y1, x2, y2 = o.box
            assert 0 <= x1 < x2 <= RIG.width and 0 <= y1 < y2 <= RIG.height
            assert 0.0 <= o.occluded <= 1.0
            assert o.label in ("crab", "scallop", "tag")
        kinds = {o.label for o in truth.objects if o.occluded <= 0.65}
        expected = "crab" if "crab" in kinds else "scallop" if "scallop" in kinds else "empty"
        assert truth.scene_label == expected
    assert labels == {"crab", "scallop", "empty"}


def test_moving_pose_is_smooth_rigid_and_starts_at_identity(moving_world: World) -> None:
    p0 = np.array(moving_world.render(0)[2].pose).reshape(3, 4)
    assert np.allclose(p0, np.hstack([np.eye(3), np.zeros((3, 1))]), atol=1e-9)
    prev = p0
    for i in range(1, 30):
        p = np.array(moving_world.render(i)[2].pose).reshape(3, 4)
        r = p[:, :3]
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-9)
        step = np.linalg.norm(p[:, 3] - prev[:, 3])
        assert 0.0 < step < 0.05  # about 0.15 m/s at 15 pairs/s
        prev = p


def _floor_match(left: np.ndarray, right: np.ndarray, u: int, v: int, d_range: range
                 ) -> int:
    """Disparity of the best right-image match of a left patch (sum of absolute differences)."""
    def zero_mean(a: np.ndarray) -> np.ndarray:
        a = a.astype(np.float64)
        return a - a.mean()

    patch = zero_mean(left[v - 6:v + 7, u - 6:u + 7])
    costs = [np.abs(zero_mean(right[v - 6:v + 7, u - d - 6:u - d + 7]) - patch).sum()
             for d in d_range]
    return d_range[int(np.argmin(costs))]


def test_a_moving_rig_never_flags_image_health(moving_world: World) -> None:
    """Issue 33: the floor passing under a moving rig, animals coming and going, is no
    fouling and no turbidity (the watch's windows scaled down with its sampling)."""
    cfg = ImageHealthConfig(every_s=5.0, baseline_s=50.0, window_s=40.0, hold_s=30.0)
    watch = Watch(cfg)
    for t in range(0, 200, 5):
        watch.add(float(t), measure(moving_world.render(int(t * moving_world.rate_hz))[0]))
        assert watch.view.state in ("learning", "ok"), (t, watch.view)
    assert watch.view.state == "ok" and watch.view.samples == 40


def test_disparity_matches_the_floor_depth() -> None:
    world = World(RIG, seed=2, moving=False, rate_hz=15.0,
                  options=SynthOptions(noise=0.0, snow=0.0, density=0.0))
    left, right, _ = world.render(0)
    pose = world.traj.floor_pose(0.0)
    w2c = inv_pose(pose)
    boxes = [g[:2] + g[3].shape[::-1] for b in world.boulders
             if (g := world._warp(b, w2c, 0, None)) is not None]
    checked = 0
    for u, v in ((160, 120), (100, 150), (220, 90), (60, 100), (260, 140), (130, 60)):
        if any(x0 - 8 <= u <= x0 + w + 8 and y0 - 8 <= v <= y0 + h + 8
               for x0, y0, w, h in boxes):
            continue  # boulders stand above the floor
        checked += 1
        ray = np.array([(u - RIG.cx) / RIG.fx, (v - RIG.cy) / RIG.fy, 1.0])
        d = pose[:3, :3] @ ray
        t = pose[2, 3] / -d[2]
        for _ in range(8):
            p = pose[:3, 3] + t * d
            h = float(world.floor.height_at(np.array([[p[0]]]), np.array([[p[1]]]))[0, 0])
            t = (pose[2, 3] - h) / -d[2]
        expected = RIG.fx * RIG.baseline_m / t
        found = _floor_match(left, right, u, v, range(0, 40))
        assert abs(found - expected) <= 1.0, (u, v, found, expected)
    assert checked >= 3


def test_tags_have_truth_and_poses(static_world: World) -> None:
    truth = static_world.render(0)[2]
    tags = [o for o in truth.objects if o.label == "tag"]
    assert sorted(o.id for o in tags) == [0, 1]
    poses = static_world.tag_poses()
    for o in tags:
        centre = poses[o.id][:3, 3]
        u = RIG.fx * centre[0] / centre[2] + RIG.cx
        v = RIG.fy * centre[1] / centre[2] + RIG.cy
        x1, y1, x2, y2 = o.box
        assert x1 < u < x2 and y1 < v < y2
        assert math.isclose(o.depth_m, centre[2], rel_tol=0.05)


@pytest.mark.parametrize(
    ("options", "error"),
    [
        ({"dens": 1}, "source.options.dens: unknown option"),
        ({"density": 9}, "source.options.density"),
        ({"density": "lots"}, "source.options.density"),
        ({"snow": -1}, "source.options.snow"),
        ({"tilt_deg": 10}, "source.options.tilt_deg"),
        ({"tags": 1.5}, "source.options.tags"),
        ([1, 2], "source.options: expected a mapping"),
    ],
)
def test_bad_options_are_rejected_by_name(options: object, error: str) -> None:
    with pytest.raises(ConfigError, match=error.replace(".", r"\.")):
        parse_options(options)


@pytest.mark.parametrize(
    ("cfg", "error"),
    [
        (SourceConfig(seed=-1, width=320, height=180), "source.seed"),
        (SourceConfig(width=640, height=180), "source.width/height"),
        (SourceConfig(width=320, height=180, options={"blurr": 2}), "source.options.blurr"),
    ],
)
def test_bad_source_settings_name_the_parameter(cfg: SourceConfig, error: str) -> None:
    with pytest.raises(ConfigError, match=error.replace(".", r"\.")):
        SyntheticSource(cfg, RIG)


def test_source_reads_monotonic_frames_with_truth() -> None:
    src = SyntheticSource(SourceConfig(width=320, height=180, seed=1, options={"snow": 0.5}), RIG)
    src.open()
    a, b = src.read(), src.read()
    src.close()
    assert b.t_left_ns >= a.t_left_ns and a.truth is not None and b.truth is not None
    assert a.left.shape == (180, 320, 3) and not np.array_equal(a.left, b.left)
