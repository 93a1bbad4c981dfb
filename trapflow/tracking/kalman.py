"""A constant-velocity Kalman filter on one box (centre x, y, width, height) in continuous
time: the detector sees pairs at irregular intervals, so every step takes its own dt."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_DIM = 4  # measured: cx, cy, w, h; the state adds their rates
_H = np.hstack([np.eye(_DIM), np.zeros((_DIM, _DIM))])


@dataclass(frozen=True)
class Noise:
    """Noise levels relative to the box height, so one setting fits near and far animals
    (defaults tuned with the tracker's thresholds, trapflow.tracking.tracker.TrackerConfig;
    `turn` on the synthetic world and real fish together, docs/benchmarks.md "Tracking on
    real fish").

    Acceleration: the synthetic world's animals move about 0.7 box heights a second and
    accelerate about 0.5 box heights/s^2 per sqrt(Hz); the real crocea fish (realdata 08)
    about 4-5 and 7-12. One constant fitted to the first made the filter trust a straight
    line through every turn of the second, and a turning fish's predicted box slid onto its
    neighbour (about three times the id switches of a filter that follows turns). A turn
    at rate w of an animal at speed v accelerates it by w v, so the acceleration noise is
    `accel` box heights plus `turn` times the track's own speed (the part of it the filter
    is sure of, SURE_SD): a still animal keeps a narrow gate, a fast one a wide one,
    whatever the frame rate or the species."""

    measure: float = 0.08
    """Standard deviation of a detected box's centre and sides, in box heights."""
    accel: float = 0.5
    """White-noise acceleration density, in box heights per s^2 per sqrt(Hz)."""
    speed0: float = 1.0
    """Standard deviation of a new track's unknown speed, in box heights per second."""
    turn: float = 0.5
    """Added acceleration density per unit of the track's own speed, in 1/s per sqrt(Hz):
    an animal that moves fast can turn fast (a fish reverses within a fraction of a
    second), one that stands still cannot; 0: off."""


class BoxFilter:
    """State and covariance of one track's box; predict(dt) then update(box)."""

    def __init__(self, box: np.ndarray, noise: Noise) -> None:
        self.noise = noise
        self.x = np.concatenate([_centre_size(box), np.zeros(_DIM)])
        s = max(float(self.x[3]), 1.0)
        pos = (2.0 * noise.measure * s) ** 2
        vel = (noise.speed0 * s) ** 2
        self.p = np.diag([pos] * _DIM + [vel] * _DIM)

    def predict(self, dt: float) -> None:
        """Move the state dt seconds ahead (dt >= 0)."""
        if dt <= 0:
            return
        f = np.eye(2 * _DIM)
        f[:_DIM, _DIM:] = np.eye(_DIM) * dt
        q = _accel2(self.noise, self.x, self.p)
        # Integrated white-noise acceleration: the discretisation exact for any dt.
        blk = q * np.array([[dt ** 3 / 3.0, dt ** 2 / 2.0], [dt ** 2 / 2.0, dt]])
        qm = np.kron(blk, np.eye(_DIM))
        self.x = f @ self.x
        self.p = f @ self.p @ f.T + qm

    def update(self, box: np.ndarray) -> None:
        """Correct the state with a detected box (x1 y1 x2 y2)."""
        z = _centre_size(box)
        s = max(float(self.x[3]), 1.0)
        r = np.eye(_DIM) * (self.noise.measure * s) ** 2
        pht = self.p @ _H.T
        k = pht @ np.linalg.inv(_H @ pht + r)
        self.x = self.x + k @ (z - _H @ self.x)
        self.p = (np.eye(2 * _DIM) - k @ _H) @ self.p

    def distance2(self, boxes: np.ndarray) -> np.ndarray:
        """Squared Mahalanobis distance of each detected box (N, 4; x1 y1 x2 y2) from the
        predicted one, under the prediction's covariance plus the measurement noise: about
        chi-square with 4 degrees of freedom for a box of this track, however long the
        track went unseen (its covariance has grown with the time)."""
        out: np.ndarray = distance2_many([self], boxes)[0]
        return out

    def box(self) -> np.ndarray:
        """The state's box as x1 y1 x2 y2 (sides kept at least one pixel)."""
        cx, cy = self.x[0], self.x[1]
        w, h = max(float(self.x[2]), 1.0), max(float(self.x[3]), 1.0)
        return np.array([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2])


def predict_many(filters: list[BoxFilter], dts: np.ndarray) -> None:
    """BoxFilter.predict of each filter by its dt (dt <= 0: unchanged), as one numpy pass
    over all of them (a frame of 1,000 tracks, one at a time, took 0.1 s)."""
    dts = np.asarray(dts, dtype=float)
    idx = np.flatnonzero(dts > 0)
    if len(idx) == 0:
        return
    group = [filters[i] for i in idx]
    dt = dts[idx]
    x = np.stack([f.x for f in group])
    p = np.stack([f.p for f in group])
    f = np.broadcast_to(np.eye(2 * _DIM), (len(group), 2 * _DIM, 2 * _DIM)).copy()
    f[:, :_DIM, _DIM:] = np.eye(_DIM) * dt[:, None, None]
    q = np.array([_accel2(g.noise, g.x, g.p) for g in group])
    # Integrated white-noise acceleration per filter, as predict() makes it.
    blk = q[:, None, None] * np.array([[dt ** 3 / 3.0, dt ** 2 / 2.0],
                                       [dt ** 2 / 2.0, dt]]).transpose(2, 0, 1)
    qm = np.einsum("tab,ij->taibj", blk, np.eye(_DIM)).reshape(len(group), 2 * _DIM, 2 * _DIM)
    x = np.einsum("tij,tj->ti", f, x)
    p = f @ p @ np.swapaxes(f, 1, 2) + qm
    for k, g in enumerate(group):
        g.x, g.p = x[k], p[k]


def update_many(filters: list[BoxFilter], boxes: np.ndarray) -> None:
    """BoxFilter.update of each filter with its box (N, 4), as one numpy pass."""
    if not filters:
        return
    b = np.asarray(boxes, dtype=float).reshape(-1, 4)
    z = np.stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2,
                  b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]], axis=1)
    x = np.stack([f.x for f in filters])
    p = np.stack([f.p for f in filters])
    r = np.array([(f.noise.measure * max(float(f.x[3]), 1.0)) ** 2 for f in filters])
    pht = p[:, :, :_DIM]  # P @ H.T: H selects the measured half of the state
    k = pht @ np.linalg.inv(p[:, :_DIM, :_DIM] + r[:, None, None] * np.eye(_DIM))
    x = x + np.einsum("tij,tj->ti", k, z - x[:, :_DIM])
    p = p - k @ p[:, :_DIM, :]  # (I - K H) P
    for n, f in enumerate(filters):
        f.x, f.p = x[n], p[n]


# Tracks x boxes values of one block of distance2_many (a few MB of temporaries).
BLOCK_VALUES = 1 << 18


def distance2_many(filters: list[BoxFilter], boxes: np.ndarray) -> np.ndarray:
    """BoxFilter.distance2 of every filter (rows) to every box (N, 4; columns), computed a
    block of filters at a time: bounded memory, no Python loop over the boxes."""
    if not filters or len(boxes) == 0:
        return np.zeros((len(filters), len(boxes)))
    b = np.asarray(boxes, dtype=float).reshape(-1, 4)
    z_all = np.stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2,
                      b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]], axis=1)
    out = np.empty((len(filters), len(b)))
    step = max(1, BLOCK_VALUES // len(b))
    for start in range(0, len(filters), step):
        block = filters[start:start + step]
        x = np.stack([f.x[:_DIM] for f in block])  # _H @ state: the measured part
        meas = np.array([(f.noise.measure * max(float(f.x[3]), 1.0)) ** 2 for f in block])
        cov = np.stack([f.p[:_DIM, :_DIM] for f in block]) + meas[:, None, None] * np.eye(_DIM)
        z = z_all[None, :, :] - x[:, None, :]
        out[start:start + len(block)] = np.einsum("tni,tij,tnj->tn", z, np.linalg.inv(cov), z)
    return out


# The turn term takes the part of a track's speed its filter is sure of: the estimate less
# this many standard deviations. The whole estimate fed back on itself: a jittery slow
# animal's noisy speed widened its noise, which let its speed follow the jitter more (on
# the synthetic world's held-out seeds IDF1 fell from 86.8 to 81.7 at every pair).
SURE_SD = 2.0


def _accel2(noise: Noise, x: np.ndarray, p: np.ndarray) -> float:
    """The squared acceleration density of a state (x, covariance p): `accel` box heights,
    plus `turn` times the speed it is sure of (pixels per second, SURE_SD below the
    estimate)."""
    s = max(float(x[3]), 1.0)
    sd = float(np.sqrt(max(p[4, 4] + p[5, 5], 0.0) / 2.0))
    v = max(0.0, float(np.hypot(x[4], x[5])) - SURE_SD * sd)
    return float((noise.accel * s + noise.turn * v) ** 2)


def _centre_size(box: np.ndarray) -> np.ndarray:
    x1, y1, x2, y2 = (float(v) for v in box)
    return np.array([(x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1])
