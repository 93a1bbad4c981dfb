"""KITTI-style odometry error: relative translation error over path segments of fixed length."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def _inv(t: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    r = t[:3, :3].T
    out[:3, :3], out[:3, 3] = r, -r @ t[:3, 3]
    return out


def as_4x4(pose12: Sequence[float]) -> np.ndarray:
    """A 4x4 transform from a row-major 3x4 [R|t] (12 numbers)."""
    out = np.eye(4)
    out[:3, :4] = np.asarray(pose12, float).reshape(3, 4)
    return out


def path_length(poses: Sequence[np.ndarray]) -> np.ndarray:
    """Distance travelled up to each pose (camera centres), starting at 0."""
    centres = np.array([p[:3, 3] for p in poses])
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def segment_errors(
    truth: Sequence[np.ndarray],
    estimate: Sequence[np.ndarray],
    lengths: Sequence[float],
    step: int = 5,
) -> list[tuple[float, float]]:
    """(segment length, translation error / length) for every start frame (every `step`).

    Poses are camera-to-world 4x4; the two trajectories may live in different world frames.
    """
    dist = path_length(truth)
    out: list[tuple[float, float]] = []
    for first in range(0, len(truth), step):
        for length in lengths:
            after = np.flatnonzero(dist >= dist[first] + length)
            if after.size == 0:
                continue
            last = int(after[0])
            t_rel = _inv(truth[first]) @ truth[last]
            e_rel = _inv(estimate[first]) @ estimate[last]
            err = _inv(e_rel) @ t_rel
            out.append((float(length), float(np.linalg.norm(err[:3, 3])) / float(length)))
    return out


def drift_percent(
    truth: Sequence[np.ndarray],
    estimate: Sequence[np.ndarray],
    lengths: Sequence[float],
    step: int = 5,
) -> float:
    """Mean translational drift in % of distance travelled over the given segment lengths."""
    errs = segment_errors(truth, estimate, lengths, step)
    if not errs:
        raise ValueError(f"path of {path_length(truth)[-1]:.2f} m is shorter than every segment")
    return 100.0 * float(np.mean([e for _, e in errs]))


def end_drift_percent(truth: Sequence[np.ndarray], estimate: Sequence[np.ndarray]) -> float:
    """Error of the final position relative to the start, in % of the path length."""
    t_rel = _inv(truth[0]) @ truth[-1]
    e_rel = _inv(estimate[0]) @ estimate[-1]
    return 100.0 * float(np.linalg.norm(t_rel[:3, 3] - e_rel[:3, 3]) / path_length(truth)[-1])
