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
    (defaults tuned with the tracker's thresholds, trapflow.tracking.tracker.TrackerConfig)."""

    measure: float = 0.08
    """Standard deviation of a detected box's centre and sides, in box heights."""
    accel: float = 0.5
    """White-noise acceleration density, in box heights per s^2 per sqrt(Hz)."""
    speed0: float = 1.0
    """Standard deviation of a new track's unknown speed, in box heights per second."""


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
        s = max(float(self.x[3]), 1.0)
        q = (self.noise.accel * s) ** 2
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
        if len(boxes) == 0:
            return np.zeros(0)
        z = np.array([_centre_size(b) for b in boxes]) - _H @ self.x
        s = max(float(self.x[3]), 1.0)
        cov = _H @ self.p @ _H.T + np.eye(_DIM) * (self.noise.measure * s) ** 2
        out: np.ndarray = np.einsum("ni,ij,nj->n", z, np.linalg.inv(cov), z)
        return out

    def box(self) -> np.ndarray:
        """The state's box as x1 y1 x2 y2 (sides kept at least one pixel)."""
        cx, cy = self.x[0], self.x[1]
        w, h = max(float(self.x[2]), 1.0), max(float(self.x[3]), 1.0)
        return np.array([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2])


def _centre_size(box: np.ndarray) -> np.ndarray:
    x1, y1, x2, y2 = (float(v) for v in box)
    return np.array([(x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1])
