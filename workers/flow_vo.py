"""A light frame-to-frame odometry: ORB matches on the left view, a robust 2-D similarity
lifted to [R|t] (yaw about the optical axis, translation scaled by the floor depth).

Stands in where full stereo odometry is too heavy; re-initialises on gaps.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import cv2
import msgspec
import numpy as np

from trapflow.plugin import Context, Pair, StereoVO, Worker, WorkerError

_I = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


class FlowParams(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Parameters of the flow odometry."""

    features: int = 500
    min_inliers: int = 20
    scale: float = 0.5
    depth_m: float = 1.5  # assumed distance to the floor, turns pixels into metres


class FlowOdometry(Worker):
    """Similarity transform between consecutive left images."""

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        try:
            self.p = msgspec.convert(dict(params), FlowParams)
        except msgspec.ValidationError as exc:
            raise WorkerError(f"pools.{ctx.pool}.params: {exc}") from None
        self.fx = ctx.rig.fx
        self.orb = cv2.ORB.create(self.p.features)
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self.prev: tuple[Any, Any] | None = None
        self.pose = np.eye(4)

    def process(self, pair: Pair) -> StereoVO:
        s = self.p.scale
        gray = cv2.cvtColor(cv2.resize(pair.left, None, fx=s, fy=s), cv2.COLOR_BGR2GRAY)
        kp, des = self.orb.detectAndCompute(gray, None)
        prev, self.prev = self.prev, (kp, des)
        if pair.gap > 0 or prev is None or des is None or prev[1] is None:
            return StereoVO(ok=False, reinit=True, pose=self._pose())
        matches = self.matcher.match(prev[1], des)
        if len(matches) < self.p.min_inliers:
            return StereoVO(ok=False, pose=self._pose())
        a = np.array([prev[0][m.queryIdx].pt for m in matches], dtype=np.float32)
        b = np.array([kp[m.trainIdx].pt for m in matches], dtype=np.float32)
        m, inl = cv2.estimateAffinePartial2D(a, b, method=cv2.RANSAC, ransacReprojThreshold=2.0)
        n = int(inl.sum()) if inl is not None else 0
        if m is None or n < self.p.min_inliers:
            return StereoVO(ok=False, inliers=n, pose=self._pose())
        yaw = math.atan2(m[1, 0], m[0, 0])
        c, si = math.cos(yaw), math.sin(yaw)
        # Image motion of the floor is the opposite of the camera's motion.
        k = self.p.depth_m / (self.fx * s)
        t = (-float(m[0, 2]) * k, -float(m[1, 2]) * k, 0.0)
        rot = (c, si, 0.0, -si, c, 0.0, 0.0, 0.0, 1.0)
        step = np.eye(4)
        step[:3, :3] = np.array(rot).reshape(3, 3)
        step[:3, 3] = t
        self.pose = self.pose @ step
        return StereoVO(ok=True, rotation=rot, translation=t, pose=self._pose(), inliers=n)

    def _pose(self) -> tuple[float, ...]:
        return tuple(float(v) for v in self.pose[:3, :].ravel())
