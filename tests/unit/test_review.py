"""The review queue's pure core: the band per label, the seeded audit draw, a label new to
the run, and each live track's best view."""

from __future__ import annotations

import cv2
import msgspec
import numpy as np
import pytest

from trapflow.config.schema import ReviewConfig, from_data
from trapflow.errors import ConfigError
from trapflow.tracking import review


def _track(tid: int, label: str, conf: float) -> dict:
    return {"track": {"id": tid, "label": label, "best_confidence": conf,
                      "first_s": 10.0, "last_s": 12.0}}


def test_band_rejects_below_and_confirms_above() -> None:
    cfg = ReviewConfig(low=0.3, high=0.65, audit=0.0, new_label=False)
    assert review.reasons(cfg, "mono", 1, "crab", 0.29, new=False) == []
    assert review.reasons(cfg, "mono", 1, "crab", 0.3, new=False) == ["band"]
    assert review.reasons(cfg, "mono", 1, "crab", 0.649, new=False) == ["band"]
    assert review.reasons(cfg, "mono", 1, "crab", 0.65, new=False) == []


def test_a_label_has_its_own_band() -> None:
    cfg = msgspec.convert({"labels": {"scallop": {"high": 0.9}}, "audit": 0.0}, ReviewConfig)
    assert review.reasons(cfg, "mono", 1, "scallop", 0.8, new=False) == ["band"]
    assert review.reasons(cfg, "mono", 1, "crab", 0.8, new=False) == []
    assert review.rule_for(cfg, "scallop") == review.Rule(0.15, 0.9, 0.0, True)


def test_audit_draws_about_its_share_of_confident_tracks_and_the_same_ones_again() -> None:
    cfg = ReviewConfig(audit=0.02, new_label=False)
    drawn = [t for t in range(1, 20001)
             if review.reasons(cfg, "mono", t, "crab", 0.95, new=False) == ["audit"]]
    assert 320 <= len(drawn) <= 480  # 2 % of 20,000, give or take 4 standard deviations
    again = [t for t in range(1, 20001)
             if review.reasons(cfg, "mono", t, "crab", 0.95, new=False)]
    assert again == drawn  # a restart draws the same tracks
    other = ReviewConfig(audit=0.02, new_label=False, seed=1)
    assert drawn != [t for t in range(1, 20001)
                     if review.reasons(other, "mono", t, "crab", 0.95, new=False)]
    # Below the band nothing is audited.
    assert not any(review.reasons(cfg, "mono", t, "crab", 0.1, new=False) for t in drawn)


def test_a_new_label_is_reviewed_once_per_run_unless_its_rule_says_not() -> None:
    cfg = msgspec.convert({"audit": 0.0, "labels": {"empty": {"new_label": False}}},
                          ReviewConfig)
    rev = review.Reviewer(cfg, "mono")
    first = rev.ended(_track(1, "crab", 0.9))
    assert first is not None and first["review"]["reasons"] == ["new_label"]
    assert rev.ended(_track(2, "crab", 0.9)) is None
    assert rev.ended(_track(3, "empty", 0.9)) is None
    got = rev.ended(_track(4, "crab", 0.5))
    assert got is not None and got["review"]["reasons"] == ["band"]


def test_the_best_view_is_kept_and_goes_with_the_review_line() -> None:
    rev = review.Reviewer(ReviewConfig(audit=0.0), "mono")
    low = review.BestView(0.2, 0.6, (0, 0, 10, 10), 11.0, b"a")
    high = review.BestView(0.5, 0.7, (5, 5, 50, 50), 11.5, b"b")
    assert rev.offer(7, low) and rev.offer(7, high) and not rev.offer(7, low)
    line = rev.ended(_track(7, "crab", 0.6))
    assert line is not None
    assert line["review"]["jpeg"] == b"b" and line["review"]["view_s"] == 11.5
    assert 7 not in rev.views


def test_sharp_large_confident_views_score_higher() -> None:
    rng = np.random.default_rng(1)
    sharp = rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)
    blurred = cv2.GaussianBlur(sharp, (0, 0), 4)
    s_sharp, s_blur = review.sharpness(sharp), review.sharpness(blurred)
    assert s_sharp > 10 * s_blur
    assert review.view_score(0.8, 64, s_sharp, 128) > review.view_score(0.8, 64, s_blur, 128)
    assert review.view_score(0.8, 128, s_sharp, 128) > review.view_score(0.8, 32, s_sharp, 128)
    assert review.view_score(0.9, 64, s_sharp, 128) > review.view_score(0.6, 64, s_sharp, 128)


def test_config_refuses_a_band_upside_down() -> None:
    with pytest.raises(ConfigError, match="low <= high"):
        from_data({"review": {"labels": {"crab": {"low": 0.8}}}})


def test_the_observer_queues_finished_tracks_for_review() -> None:
    from trapflow.config.schema import ObserveConfig
    from trapflow.tracking.stage import Observer

    obs = Observer(ObserveConfig(), review=ReviewConfig(audit=0.0), pool="mono")
    got = []
    for i in range(6):  # a crab in the band (0.55), then a confident one: a known label
        box = [100.0 + i, 100.0, 150.0 + i, 140.0]
        got.append(obs.feed(int(i * 0.2e9), [{"label": "crab", "confidence": 0.55,
                                               "box": box}]))
    got.append(obs.finish())
    reviews = [r["review"] for g in got for r in g.reviews]
    assert [(r["track"], r["reasons"]) for r in reviews] == [(1, ["band", "new_label"])]
    assert "jpeg" not in reviews[0]  # no view was offered
    again = Observer(ObserveConfig(), review=ReviewConfig(enabled=False), pool="mono")
    assert not again.finish().reviews
