"""A track's speed along its path (Camtrap DP's individualSpeed, the average movement speed)
and, apart, over its net displacement. Regression: a crab that crossed the view and came
back was given 0.011 m/s, the slope of a straight line through its positions, against
about 0.12 m/s along its path."""

from __future__ import annotations

import numpy as np
import pytest

from trapflow.tracking.speed import speeds
from trapflow.tracking.stage import View, aggregate

RATE_HZ = 5.0
NOISE_M = 0.008  # a view's stereo position noise at about 1.3 m (range_sd_m)


def _there_and_back(speed: float, leg_s: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """An animal walking `speed` m/s across the view along x for `leg_s` seconds and back
    the same way, at 1.3 m, its positions seen with stereo noise."""
    t = np.arange(0.0, 2 * leg_s + 1e-9, 1 / RATE_HZ)
    x = np.where(t <= leg_s, speed * t, speed * (2 * leg_s - t)) - 0.6
    pos = np.stack([x, np.full_like(t, 0.2), np.full_like(t, 1.3)], axis=1)
    return t, pos + np.random.default_rng(seed).normal(0.0, NOISE_M, pos.shape)


@pytest.mark.parametrize("seed", range(5))
def test_a_track_that_goes_and_comes_back(seed: int) -> None:
    t, pos = _there_and_back(0.12, 10.0, seed)
    got = speeds(t, pos)
    assert got["speed_m_s"] == pytest.approx(0.12, rel=0.10)
    assert got["net_speed_m_s"] < 0.02  # its net displacement: nearly none
    assert got["speed_sd_m_s"] < 0.05
    # The same through the observation stage, as tracks.jsonl gets it.
    views = [View(100.0 + ti, (p[0], p[1], p[2]), None, None) for ti, p in zip(t, pos,
                                                                                strict=True)]
    rec = aggregate(views)
    assert rec["speed_m_s"] == pytest.approx(0.12, rel=0.10)
    assert rec["speed_frame"] == "camera" and rec["net_speed_m_s"] < 0.02


def test_a_straight_walk_has_one_speed() -> None:
    t = np.arange(0.0, 4.0, 0.2)
    pos = np.stack([0.1 * t, 0.05 * t, 1.5 + 0.0 * t], axis=1)
    got = speeds(t, pos)
    truth = float(np.hypot(0.1, 0.05))
    assert got["speed_m_s"] == pytest.approx(truth, abs=1e-3)
    assert got["net_speed_m_s"] == pytest.approx(truth, abs=1e-3)
    assert got["speed_sd_m_s"] == pytest.approx(0.0, abs=1e-3)


def test_a_still_animal_hardly_moves_by_its_noise() -> None:
    t = np.arange(0.0, 20.0, 1 / RATE_HZ)
    pos = np.random.default_rng(7).normal(0.0, NOISE_M, (len(t), 3)) + [0.0, 0.2, 1.3]
    assert speeds(t, pos)["speed_m_s"] < 0.012  # a view-to-view path: about 0.06 m/s


def test_a_short_track_is_cut_into_three_steps() -> None:
    t = np.array([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    pos = np.stack([0.3 * t, 0.0 * t, 1.0 + 0.0 * t], axis=1)
    assert speeds(t, pos)["speed_m_s"] == pytest.approx(0.3, abs=1e-3)
