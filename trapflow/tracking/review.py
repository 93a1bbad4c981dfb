"""Which finished tracks a person should see, and each live track's best view, pure.

A track is queued for review when its label's confidence lies in the label's review band
(between auto-reject, `low`, and auto-confirm, `high`), when it is drawn for the audit of
confident tracks (`audit`, a share), or when its label is new to the run (`new_label`);
each rule per label (`review.labels`), else the section's. The audit draw is a hash of the
seed, the pool and the track's id, not a random generator: the same track of the same run
is drawn or not whatever restarts happened in between, so a power cut neither draws a track
twice nor skips the draw.

A track's best view is the box with the highest score: confidence x size (the crop's
longest side against `review.crop_px`, at most 1) x sharpness (the variance of the
Laplacian of the crop shrunk to 64 px, as s / (s + 100)): confident, large and sharp.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from trapflow.config.schema import ReviewConfig

# Reasons a track is queued, in the review file's `reasons`.
BAND, AUDIT, NEW_LABEL = "band", "audit", "new_label"
# The side a crop is shrunk to before its sharpness is measured (so it does not grow with
# the crop's size), and the sharpness at which the score's sharpness term is one half.
SHARPNESS_PX = 64
SHARPNESS_HALF = 100.0


@dataclass(frozen=True)
class Rule:
    """One label's review rule, resolved."""

    low: float
    high: float
    audit: float
    new_label: bool


def rule_for(cfg: ReviewConfig, label: str) -> Rule:
    """A label's rule: its own keys (`review.labels`), the section's for the rest."""
    own = cfg.labels.get(label)

    def pick(name: str) -> Any:
        mine = None if own is None else getattr(own, name)
        return getattr(cfg, name) if mine is None else mine

    return Rule(pick("low"), pick("high"), pick("audit"), pick("new_label"))


def audit_draw(seed: int, pool: str, track: int) -> float:
    """A number in [0, 1) fixed by (seed, pool, track): the track is audited when it is
    below the label's `audit` share."""
    digest = hashlib.blake2b(f"{seed}:{pool}:{track}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big") / 2.0**64


def reasons(cfg: ReviewConfig, pool: str, track: int, label: str, confidence: float,
            new: bool) -> list[str]:
    """Why a finished track is queued (empty: it is not): its label's confidence in the
    band, drawn for the audit (confirmed tracks only), its label new to the run."""
    rule = rule_for(cfg, label)
    out: list[str] = []
    if rule.low <= confidence < rule.high:
        out.append(BAND)
    elif confidence >= rule.high and audit_draw(cfg.seed, pool, track) < rule.audit:
        out.append(AUDIT)
    if new and rule.new_label:
        out.append(NEW_LABEL)
    return out


def sharpness(crop: np.ndarray) -> float:
    """Variance of the Laplacian of a BGR or grey crop shrunk to SHARPNESS_PX."""
    grey = crop if crop.ndim == 2 else cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY)
    h, w = grey.shape
    scale = SHARPNESS_PX / max(h, w, 1)
    if scale < 1:
        grey = cv2.resize(grey, (max(1, round(w * scale)), max(1, round(h * scale))),
                          interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def view_score(confidence: float, side_px: float, sharp: float, crop_px: int) -> float:
    """A view's score: confidence x size term x sharpness term, each in [0, 1]."""
    size = min(1.0, side_px / crop_px)
    return confidence * size * (sharp / (sharp + SHARPNESS_HALF))


@dataclass
class BestView:
    """A live track's best view so far."""

    score: float
    confidence: float
    box: tuple[float, float, float, float]
    t_s: float  # capture time (the wall clock's label)
    jpeg: bytes  # the crop


@dataclass
class Reviewer:
    """One detector pool's review memory: each live track's best view, and the labels the
    run has had a track of (for `new_label`). Kept in the observation checkpoint."""

    cfg: ReviewConfig
    pool: str
    views: dict[int, BestView] = field(default_factory=dict)
    labels: set[str] = field(default_factory=set)

    def offer(self, track: int, view: BestView) -> bool:
        """A view of a live track: kept when it beats the one kept (True)."""
        kept = self.views.get(track)
        if kept is not None and kept.score >= view.score:
            return False
        self.views[track] = view
        return True

    def offer_crop(self, track: int, confidence: float,
                   box: tuple[float, float, float, float], sharp: float, jpeg: bytes,
                   t_s: float) -> bool:
        """A detector worker's crop of a live track's box (its longest side in frame
        pixels, its sharpness measured by the worker): kept when it scores best (True)."""
        side = max(box[2] - box[0], box[3] - box[1])
        score = view_score(confidence, side, sharp, self.cfg.crop_px)
        return self.offer(track, BestView(score, confidence, box, t_s, jpeg))

    def ended(self, record: dict[str, Any]) -> dict[str, Any] | None:
        """A finished track (its tracks.jsonl object): its review line when it is queued
        (the best view's crop under `jpeg`, bytes, for the caller to write), else None."""
        t = record["track"]
        view = self.views.pop(t["id"], None)
        new = t["label"] not in self.labels
        self.labels.add(t["label"])
        why = reasons(self.cfg, self.pool, t["id"], t["label"], t["best_confidence"], new)
        if not why:
            return None
        line: dict[str, Any] = {"pool": self.pool, "track": t["id"], "label": t["label"],
                                "confidence": t["best_confidence"], "reasons": why,
                                "first_s": t["first_s"], "last_s": t["last_s"]}
        if view is not None:
            line.update(view_s=round(view.t_s, 3), view_box=[round(v, 1) for v in view.box],
                        view_confidence=round(view.confidence, 3), jpeg=view.jpeg)
        return {"review": line}
