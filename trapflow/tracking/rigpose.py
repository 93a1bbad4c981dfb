"""The rig's own motion for the observation stage, pure: visual odometry's accumulated poses by
capture time, so that a track's speed is taken over the ground, not against a drifting rig.

A VO re-initialisation (after a gap or a lost track) starts a new chain whose origin is not
tied to the last one: positions are compared only within one chain (`segment`).
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np

# A view takes the pose of a pair at most this far from its own capture time (the same pair
# in practice: every pool sees the pairs of one capture; 0.15 s spans a dropped pair at 15 Hz).
POSE_TOLERANCE_S = 0.15
# Poses older than the newest by this are forgotten: tracks end after a few seconds unseen,
# and a track that lasted longer keeps the poses of its last two minutes.
KEEP_S = 120.0


@dataclass
class RigPoses:
    """Left-camera-to-world poses (4x4) of the pairs VO saw, in capture-time order."""

    tolerance_s: float = POSE_TOLERANCE_S
    keep_s: float = KEEP_S
    times: list[float] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    segments: list[int] = field(default_factory=list)
    segment: int = 0  # the chain new poses belong to

    def add(self, t_s: float, pose: tuple[float, ...], ok: bool, reinit: bool) -> None:
        """One VO result: its capture time, accumulated 3x4 pose (row major), ok and reinit.

        A result that is not ok carries the last good pose, not its own: it is skipped. A
        re-initialisation starts a new chain at the pose it carries.
        """
        if reinit:
            self.segment += 1
        if len(pose) != 12 or not (ok or reinit):
            return
        m = np.eye(4)
        m[:3, :] = np.asarray(pose, float).reshape(3, 4)
        i = bisect.bisect(self.times, t_s)
        self.times.insert(i, t_s)
        self.poses.insert(i, m)
        self.segments.insert(i, self.segment)
        old = bisect.bisect_left(self.times, self.times[-1] - self.keep_s)
        if old:
            del self.times[:old], self.poses[:old], self.segments[:old]

    def __bool__(self) -> bool:
        return bool(self.times)

    def at(self, t_s: float) -> tuple[int, np.ndarray] | None:
        """(chain, pose) at capture time t_s: the nearest pose within the tolerance, its
        translation interpolated between two poses of one chain around t_s; None if none."""
        i = bisect.bisect(self.times, t_s)
        near = [k for k in (i - 1, i) if 0 <= k < len(self.times)
                and abs(self.times[k] - t_s) <= self.tolerance_s]
        if not near:
            return None
        k = min(near, key=lambda k: abs(self.times[k] - t_s))
        pose = self.poses[k]
        if len(near) == 2 and self.segments[i - 1] == self.segments[i]:
            t0, t1 = self.times[i - 1], self.times[i]
            w = (t_s - t0) / (t1 - t0) if t1 > t0 else 0.0
            pose = pose.copy()
            pose[:3, 3] = (1 - w) * self.poses[i - 1][:3, 3] + w * self.poses[i][:3, 3]
        return self.segments[k], pose


def ground_positions(times: list[float], xyz: list[tuple[float, float, float]],
                     poses: RigPoses) -> tuple[np.ndarray, np.ndarray] | None:
    """The views' camera-frame positions in VO's world frame, keeping the views of the chain
    that holds most of them: (times, positions), or None when no view has a pose."""
    found = [(t, p, poses.at(t)) for t, p in zip(times, xyz, strict=True)]
    placed = [(t, p, got) for t, p, got in found if got is not None]
    if not placed:
        return None
    chains = [got[0] for _, _, got in placed]
    best = max(set(chains), key=chains.count)
    ts, world = [], []
    for t, p, (chain, pose) in placed:
        if chain == best:
            ts.append(t)
            world.append(pose[:3, :3] @ np.asarray(p, float) + pose[:3, 3])
    return np.array(ts), np.array(world)
