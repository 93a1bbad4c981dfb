"""The image-health watch: samples in, a state out (learning, ok, fouled, turbid, both).

Pure: the caller passes each sample's capture time (seconds on a clock no wall-clock step
moves) and the statistics of its left image (measure.py). Nothing here reads a clock.

- Baseline: the median of each statistic over the samples of the first `baseline_s` (at
  least MIN_BASELINE_SAMPLES of them); until then the state is `learning`. It can be given
  back (a capture restarted in the same deployment must not learn a fouled lens as clean).
- Now: the median of each statistic over the samples of the last `window_s`, over its
  baseline: a ratio, 1.0 as at the start. Medians outvote what passes: an animal, a cloud of
  snow, a turn of a moving rig.
- Flags: fouled while sharpness is below `fouled_below`, turbid while contrast is below
  `turbid_below`; each is raised only once its condition held `hold_s`, and cleared only
  once the ratio stayed above its `*_clear` level as long (hysteresis in level and time).
  The two are independent: a fouled port in turbid water raises both.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from trapflow.config.image_health import ImageHealthConfig
from trapflow.image_health.measure import Sample
from trapflow.wire.messages import ImageHealth, ImageState

MIN_BASELINE_SAMPLES = 3
RATIO_DIGITS = 3


@dataclass(frozen=True)
class Change:
    """The state changed with this sample: from `old` to the view's."""

    old: str
    view: ImageHealth


class Flag:
    """One condition with a hold time and hysteresis: `on` only once `ratio < below` held
    `hold_s`; off again only once `ratio > clear` held as long."""

    def __init__(self, below: float, clear: float, hold_s: float) -> None:
        self.below, self.clear, self.hold_s = below, clear, hold_s
        self.on = False
        self._since: float | None = None  # when the ratio first said the opposite

    def update(self, ratio: float, now: float) -> bool:
        want = not ratio > self.clear if self.on else ratio < self.below
        if want == self.on:
            self._since = None
        elif self._since is None:
            self._since = now
        if self._since is not None and now - self._since >= self.hold_s:
            self.on, self._since = want, None
        return self.on


def _median(samples: list[Sample]) -> Sample:
    return Sample(sharpness=float(np.median([s.sharpness for s in samples])),
                  contrast=float(np.median([s.contrast for s in samples])),
                  brightness=float(np.median([s.brightness for s in samples])))


def _ratio(now: float, base: float) -> float:
    return round(now / base, RATIO_DIGITS) if base > 0 else 1.0


class Watch:
    """The state machine; `due(now)` says when the next pair is worth a sample."""

    def __init__(self, cfg: ImageHealthConfig, baseline: Sample | None = None) -> None:
        self.cfg = cfg
        self.baseline = baseline
        self._start: float | None = None
        self._next: float | None = None
        self._learning: list[Sample] = []
        self._recent: deque[tuple[float, Sample]] = deque()
        self.fouled = Flag(cfg.fouled_below, cfg.fouled_clear, cfg.hold_s)
        self.turbid = Flag(cfg.turbid_below, cfg.turbid_clear, cfg.hold_s)
        self.view = ImageHealth()
        if baseline is not None:
            self.view = ImageHealth(state="ok", sharpness=1.0, contrast=1.0, brightness=1.0)

    def due(self, now: float) -> bool:
        """Whether a pair captured at `now` should be sampled (one every `every_s`)."""
        return self._next is None or now >= self._next

    def add(self, now: float, sample: Sample) -> Change | None:
        """One sampled pair's statistics at capture time `now`; a Change when the state
        changed (the baseline learnt, a flag raised or cleared), else None."""
        self._next = now + self.cfg.every_s
        if self._start is None:
            self._start = now
        self._recent.append((now, sample))
        while self._recent and self._recent[0][0] <= now - self.cfg.window_s:
            self._recent.popleft()
        if self.baseline is None:
            self._learning.append(sample)
            if (now - self._start < self.cfg.baseline_s
                    or len(self._learning) < MIN_BASELINE_SAMPLES):
                self.view = ImageHealth(state="learning", samples=self.view.samples + 1)
                return None
            self.baseline = _median(self._learning)
            self._learning = []
        return self._judge(now)

    def _judge(self, now: float) -> Change | None:
        assert self.baseline is not None
        cur = _median([s for _, s in self._recent])
        base = self.baseline
        sharp = _ratio(cur.sharpness, base.sharpness)
        contrast = _ratio(cur.contrast, base.contrast)
        fouled = self.fouled.update(sharp, now)
        turbid = self.turbid.update(contrast, now)
        state: ImageState = ("fouled+turbid" if fouled and turbid else "fouled" if fouled
                             else "turbid" if turbid else "ok")
        old = self.view
        changed = state != old.state
        self.view = ImageHealth(
            state=state, sharpness=sharp, contrast=contrast,
            brightness=_ratio(cur.brightness, base.brightness), samples=old.samples + 1,
            changes=old.changes + (changed and old.state != "learning"))
        return Change(old=old.state, view=self.view) if changed else None
