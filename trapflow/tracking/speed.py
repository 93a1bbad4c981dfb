"""A track's speed from its 3-D positions over time, pure: along its path (what Camtrap DP's
`individualSpeed` means, the average movement speed random-encounter density estimates
divide by) and, apart, over its net displacement.

Before, the one speed was the slope of a straight line through the positions: an animal
that crossed the view and came back moved 0.011 m/s by it against about 0.12 m/s along its
path, and density estimates from it came out ten times too high.

The path is measured between the means of the positions in consecutive steps of time
(`STEP_S`, shorter for a short track), not view to view: a view's stereo noise (about 1 cm)
summed over many small steps would lengthen the path of a slow animal, and of a still one
most of all. An animal that turns back within a step loses at most that step's detour.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

# The step of time the path is measured over (seconds), and the fewest steps a track's
# path is cut into (a short track's steps are shorter).
STEP_S = 1.0
MIN_STEPS = 3


def _steps(t: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean time and mean position of the views in each step of time (empty steps none)."""
    span = float(t[-1] - t[0])
    step = min(STEP_S, span / MIN_STEPS)
    last = max(1, math.ceil(span / step - 1e-9)) - 1  # the last step holds the last view
    index = np.minimum(((t - t[0]) / step).astype(int), last)
    keys, inverse = np.unique(index, return_inverse=True)
    n = np.bincount(inverse, minlength=len(keys)).astype(float)
    times = np.bincount(inverse, weights=t, minlength=len(keys)) / n
    means = np.stack([np.bincount(inverse, weights=pos[:, k], minlength=len(keys)) / n
                      for k in range(pos.shape[1])], axis=1)
    return times, means


def speeds(t: np.ndarray, pos: np.ndarray) -> dict[str, Any]:
    """A track's speeds from its positions `pos` (N x 3, metres) at times `t` (N, seconds,
    increasing, spanning more than 0): `speed_m_s`, the length of its path over the time it
    took; `speed_sd_m_s`, the standard deviation of its speed from step to step (with two
    steps or more); `net_speed_m_s`, the slope of a straight line through its positions
    over time (its net displacement's speed)."""
    slope = np.polyfit(t - t[0], pos, 1)[0]  # m/s along each axis
    out: dict[str, Any] = {}
    times, means = _steps(t, pos)
    if len(times) >= 2 and times[-1] > times[0]:
        dist = np.linalg.norm(np.diff(means, axis=0), axis=1)
        out["speed_m_s"] = round(float(dist.sum() / (times[-1] - times[0])), 3)
        if len(dist) >= 2:
            out["speed_sd_m_s"] = round(float(np.std(dist / np.diff(times), ddof=1)), 3)
    out["net_speed_m_s"] = round(float(np.linalg.norm(slope)), 3)
    return out
