"""Change detection on one pair's left image, on a small grey copy: motion yes/no, the moving
regions in full-frame pixels and a score. Owns no sockets; one detector per camera stream.

Every method sees the same small image, normalised to a fixed median (a lamp that dims or
flickers scales the whole frame, and the ratio cancels it), and the same clean-up: an
opening and a minimum blob area remove marine snow (a speck of a few pixels at full size is
a fraction of one small pixel), and a change over more than `max_cover` of the frame is
taken as a light change, not an animal: the background is learnt again from that frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

METHODS = ("average", "mog2", "knn")
# Grey level every small image is scaled to (its median): room above for bright things.
NORM_MEDIAN = 100.0

Box = tuple[int, int, int, int]


@dataclass(frozen=True)
class MotionConfig:
    """How the detector models the background; defaults chosen by benchmarks/gate.py."""

    method: str = "average"
    """average (running mean and variance per pixel), mog2 or knn (OpenCV's subtractors)."""
    width: int = 80
    """Width of the small grey image (80x45: 3600 pixels, 16x16 full-size pixels each)."""
    height: int = 45
    """Height of the small grey image."""
    alpha: float = 0.05
    """Background learning rate per pair where nothing moves (about 2 s at 10 pairs/s)."""
    alpha_moving: float = 0.005
    """Learning rate where something moves: a stopped animal fades in after ~200 pairs."""
    k_sigma: float = 4.0
    """A pixel changed when it differs from the background by k noise deviations..."""
    min_diff: float = 6.0
    """...and by at least this many grey levels (at the normalised median of 100)."""
    min_area: int = 8
    """Smallest moving blob, in small-image pixels. Marine snow at the synthetic world's
    maximum leaves blobs of 4 (one 2x2 square), a crab or scallop 12 or more."""
    max_cover: float = 0.5
    """A change over more of the frame than this is light, not an animal: re-learn."""
    warmup: int = 10
    """Pairs that build the first background; they report no motion."""
    samples: int = 4
    """Each small pixel averages samples x samples full-size pixels (0: all of them)."""

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"motion method: expected one of {', '.join(METHODS)}, "
                             f"got {self.method!r}")
        if not (8 <= self.width <= 640 and 8 <= self.height <= 480):
            raise ValueError(f"motion image: expected 8..640 x 8..480 pixels, "
                             f"got {self.width}x{self.height}")
        if not (0 < self.alpha_moving <= self.alpha <= 1):
            raise ValueError(f"motion learning rates: expected 0 < alpha_moving <= alpha <= 1, "
                             f"got {self.alpha_moving} and {self.alpha}")
        if not (self.k_sigma > 0 and self.min_diff >= 0 and self.min_area >= 1):
            raise ValueError(f"motion thresholds: expected k_sigma > 0, min_diff >= 0, "
                             f"min_area >= 1, got {self.k_sigma}, {self.min_diff}, "
                             f"{self.min_area}")
        if not 0 <= self.samples <= 16:
            raise ValueError(f"motion samples: expected 0..16 per side, got {self.samples}")
        if not 0 < self.max_cover <= 1:
            raise ValueError(f"motion max_cover: expected 0 < fraction <= 1, "
                             f"got {self.max_cover}")


@dataclass(frozen=True)
class MotionResult:
    """What the gate saw in one pair."""

    motion: bool
    score: float
    """Share of the image inside accepted moving regions, 0..1."""
    regions: tuple[Box, ...] = ()
    """Moving regions, x1 y1 x2 y2 in full-frame pixels, largest first."""
    relearnt: bool = False
    """The frame changed almost everywhere (light): the background was learnt again."""
    warming: bool = False
    """Still building the first background."""


class MotionDetector:
    """Background model of one camera stream; update() once per pair, in order."""

    def __init__(self, cfg: MotionConfig | None = None) -> None:
        self.cfg = cfg or MotionConfig()
        self._kernel = np.ones((2, 2), np.uint8)
        self._ring = np.ones((3, 3), np.uint8)
        self.reset()

    def reset(self) -> None:
        """Forget the background (the rig moved, or the stream restarted)."""
        self._n = 0
        self._bg: np.ndarray | None = None
        self._var: np.ndarray | None = None
        self._sub: Any = None
        self._prev: np.ndarray | None = None

    def update(self, image: np.ndarray) -> MotionResult:
        """One pair's left image (BGR or grey, any size): what moved against the background."""
        small = self.small(image)
        warming = self._n < self.cfg.warmup
        self._n += 1
        fg = self._foreground(small, warming)
        prev, self._prev = self._prev, small
        if warming or prev is None:
            return MotionResult(False, 0.0, warming=True)
        if cv2.countNonZero(fg) > self.cfg.max_cover * fg.size:
            self._relearn(small)
            return MotionResult(False, 0.0, relearnt=True)
        # Only a blob that also changed since the last pair moves: the ghost an animal leaves
        # where it stood (and an animal standing still) is no motion; keep-alive and tracks
        # see still animals. On the default world this halved the empty pairs called motion.
        changed = (cv2.absdiff(small, prev) > self.cfg.min_diff).astype(np.uint8)
        return self._regions(fg, changed, image.shape[1], image.shape[0])

    def small(self, image: np.ndarray) -> np.ndarray:
        """The small grey image, float32, scaled to a median of NORM_MEDIAN."""
        c = self.cfg
        size = (c.width, c.height)
        if c.samples and image.shape[1] > c.width * c.samples:
            # INTER_AREA straight from 1280x720 BGR costs 620 us here; picking every 4th
            # pixel first (nearest) and averaging those costs 117 us. Sensor noise still
            # averages over 16 samples, and a speck of snow weighs the same on average.
            mid = (c.width * c.samples, c.height * c.samples)
            image = cv2.resize(image, mid, interpolation=cv2.INTER_NEAREST)
        # Resize first, then convert: grey conversion of 80x45 instead of 1280x720.
        small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        if small.ndim == 3:
            small = cv2.cvtColor(small, cv2.COLOR_BGR2GRAY)
        med = float(np.median(small))
        out: np.ndarray = small.astype(np.float32) * np.float32(NORM_MEDIAN / max(med, 1.0))
        return out

    # --- background models -------------------------------------------------------

    def _foreground(self, g: np.ndarray, warming: bool) -> np.ndarray:
        if self.cfg.method == "average":
            return self._average(g, warming)
        return self._opencv(g, warming)

    def _average(self, g: np.ndarray, warming: bool) -> np.ndarray:
        c = self.cfg
        if self._bg is None or self._var is None:
            self._bg = g.copy()
            # The threshold starts at min_diff; the noise term takes over as it is learnt.
            self._var = np.full_like(g, (c.min_diff / c.k_sigma) ** 2)
            return np.zeros(g.shape, np.uint8)
        bg, var = self._bg, self._var
        d = cv2.absdiff(g, bg)
        thr = np.maximum(cv2.sqrt(var) * np.float32(c.k_sigma), np.float32(c.min_diff))
        fg: np.ndarray = (d > thr).astype(np.uint8)
        # Pixels next to a moving blob are partly covered by it: learning their variance
        # raised the threshold where the animal went next and split its blob in two.
        still = (1 - fg) if not warming else np.ones_like(fg)
        quiet = (1 - cv2.dilate(fg, self._ring)) if not warming else still
        # While warming the rate falls as 1/n: the first background is a plain mean.
        a = max(c.alpha, 1.0 / self._n) if warming else c.alpha
        cv2.accumulateWeighted(g, bg, a, mask=still)
        cv2.accumulateWeighted(cv2.multiply(d, d), var, a, mask=quiet)
        if not warming:
            cv2.accumulateWeighted(g, bg, c.alpha_moving, mask=fg)
        return fg

    def _opencv(self, g: np.ndarray, warming: bool) -> np.ndarray:
        c = self.cfg
        if self._sub is None:
            history = int(round(1.0 / c.alpha))
            if c.method == "mog2":
                self._sub = cv2.createBackgroundSubtractorMOG2(
                    history=history, varThreshold=c.k_sigma ** 2, detectShadows=False)
                # The same floor as the running average: k deviations >= min_diff.
                self._sub.setVarMin((c.min_diff / c.k_sigma) ** 2)
            else:
                self._sub = cv2.createBackgroundSubtractorKNN(
                    history=history, dist2Threshold=(c.k_sigma * c.min_diff / 2) ** 2,
                    detectShadows=False)
        u8 = cv2.convertScaleAbs(g)
        rate = -1.0 if warming else c.alpha  # -1: OpenCV's own 1/n while it warms up
        fg: np.ndarray = self._sub.apply(u8, learningRate=rate)
        return (fg > 0).astype(np.uint8)

    def _relearn(self, g: np.ndarray) -> None:
        if self.cfg.method == "average":
            self._bg = g.copy()
        else:  # a fresh subtractor whose first frame is this one
            self._sub = None
            self._opencv(g, warming=True)

    # --- regions ------------------------------------------------------------------

    def _regions(self, fg: np.ndarray, changed: np.ndarray, width: int, height: int
                 ) -> MotionResult:
        c = self.cfg
        opened = cv2.morphologyEx(fg, cv2.MORPH_OPEN, self._kernel)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
        if n <= 1:
            return MotionResult(False, 0.0)
        moving = set(np.unique(labels[changed > 0]).tolist())
        sx, sy = width / c.width, height / c.height
        keep = [stats[i] for i in range(1, n)
                if stats[i][cv2.CC_STAT_AREA] >= c.min_area and i in moving]
        if not keep:
            return MotionResult(False, 0.0)
        keep.sort(key=lambda s: -int(s[cv2.CC_STAT_AREA]))
        regions = tuple(
            (int(x * sx), int(y * sy), int(round((x + w) * sx)), int(round((y + h) * sy)))
            for x, y, w, h, _a in (map(int, s) for s in keep))
        area = sum(int(s[cv2.CC_STAT_AREA]) for s in keep)
        return MotionResult(True, area / fg.size, regions)
