"""A simple synthetic stereo source: a textured sea floor and a few moving blobs.

Deterministic from the seed. The realistic underwater world replaces the scene
model; the interface (Frames with Truth) stays.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from trapflow.camera import StereoRig
from trapflow.config import SourceConfig
from trapflow.messages import Truth, TruthObject
from trapflow.sources.base import Frames, Source

_IDENTITY_POSE = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
_FLOOR_DEPTH_M = 1.5


class SyntheticSource(Source):
    """Renders pairs on demand; capture paces them at the configured rate."""

    def __init__(self, cfg: SourceConfig, rig: StereoRig) -> None:
        super().__init__(rig)
        self.cfg = cfg
        self._i = 0
        rng = np.random.default_rng(cfg.seed)
        w, h = cfg.width, cfg.height
        self._disp = int(round(rig.fx * rig.baseline_m / _FLOOR_DEPTH_M))
        # Precomputed texture, wider than the view by the disparity so both eyes crop from it.
        noise = rng.integers(0, 255, size=(h // 8 + 1, (w + self._disp) // 8 + 1), dtype=np.uint8)
        tex = cv2.resize(noise, ((w + self._disp), h), interpolation=cv2.INTER_CUBIC)
        tex = cv2.GaussianBlur(tex, (0, 0), 1.5)
        floor = np.dstack([tex * 0.35, tex * 0.7, tex * 0.6]).astype(np.uint8)
        self._floor = floor
        self._crabs = rng.uniform([0.1, 0.1, 0.02, -0.03], [0.9, 0.9, 0.06, 0.03], size=(3, 4))

    def read(self) -> Frames:
        w, h = self.cfg.width, self.cfg.height
        t = self._i / self.cfg.rate_hz
        self._i += 1
        d = self._disp
        left = self._floor[:, d : d + w].copy()
        right = self._floor[:, 0:w].copy()
        objects: list[TruthObject] = []
        for k, (x0, y0, size, speed) in enumerate(self._crabs):
            cx = ((x0 + speed * t) % 1.0) * w
            cy = y0 * h
            r = size * w
            disp_obj = int(round(self.rig.fx * self.rig.baseline_m / (_FLOOR_DEPTH_M - 0.05)))
            for img, shift in ((left, 0), (right, -disp_obj + d)):
                centre = (int(cx + shift), int(cy))
                cv2.ellipse(img, centre, (int(r), int(r * 0.6)), 0, 0, 360, (30, 40, 150), -1)
            box = (max(cx - r, 0.0), max(cy - r * 0.6, 0.0),
                   min(cx + r, w - 1.0), min(cy + r * 0.6, h - 1.0))
            if box[2] > box[0]:
                objects.append(TruthObject(label="crab", box=box, depth_m=_FLOOR_DEPTH_M, id=k))
        now = time.monotonic_ns()
        truth = Truth(seq=-1, pose=_IDENTITY_POSE, objects=objects,
                      scene_label="crab" if objects else "empty")
        return Frames(left=left, right=right, t_left_ns=now, t_right_ns=now, truth=truth)
