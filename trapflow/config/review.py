"""The review queue (review:): which finished tracks are put before a person, where their
crops and lines go, and the thumbnail's byte budget over the modem (docs/review.md)."""

from __future__ import annotations

from typing import Annotated

import msgspec

from trapflow.config.base import Section as _Section

_Unit = Annotated[float, msgspec.Meta(ge=0, le=1)]


class LabelReview(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """One label's own review rule; a key left out takes the section's."""

    low: _Unit | None = None
    """Least confidence reviewed (below: rejected without review)."""
    high: _Unit | None = None
    """Confidence from which the label is confirmed without review."""
    audit: _Unit | None = None
    """Share of the confirmed tracks drawn for review all the same."""
    new_label: bool | None = None
    """Review the label's first track of the run."""


class ReviewConfig(_Section):
    """Finished tracks queued for a person's review, with their best view."""

    enabled: bool = True
    """Keep each track's best view and queue the tracks to review."""
    low: _Unit = 0.15
    """Least confidence of a track's label that is reviewed (below: rejected unseen)."""
    high: _Unit = 0.65
    """Confidence from which a track's label is confirmed without review."""
    audit: _Unit = 0.02
    """Share of the confirmed tracks drawn for review (a draw seeded by `seed`)."""
    new_label: bool = True
    """Review a label's first track of the run, whatever its confidence."""
    seed: int = 0
    """Seed of the audit draw: the same track of the same run is drawn every time."""
    labels: dict[str, LabelReview] = {}
    """Per label, its own low, high, audit or new_label."""
    file: str = "review.jsonl"
    """One line per queued track, in the run directory."""
    folder: str = "review"
    """The queued tracks' crops (JPEG), in the run directory."""
    crop_px: Annotated[int, msgspec.Meta(ge=16, le=1024)] = 256
    """Longest side of a kept crop, in pixels (larger ones are shrunk)."""
    thumbnail_bytes: Annotated[int, msgspec.Meta(ge=0, le=4096)] = 256
    """Bytes a queued track's thumbnail may take over the modem; 0: no thumbnails."""

    def __post_init__(self) -> None:
        bands = [("review", self.low, self.high)] + [
            (name, self.low if r.low is None else r.low, self.high if r.high is None else r.high)
            for name, r in self.labels.items()]
        for name, low, high in bands:
            if low > high:
                raise ValueError(f"review ({name}): expected low <= high, got low={low} "
                                 f"high={high}")
