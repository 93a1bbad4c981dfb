"""The run's observation memory across a cut (normalizer/checkpoint.py): live tracks, the
open interval and the news already given are saved and restored, so a track of before the
cut is written after it, once, and a label's news is not given twice."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from trapflow.config.schema import ObserveConfig
from trapflow.normalizer import checkpoint
from trapflow.tracking.stage import Observations, Observer

WALL0_NS = 1_764_000_000 * 10**9
PERIOD_NS = 100_000_000


def _box(x: float) -> list[dict[str, Any]]:
    return [{"timestamp": "t", "seq": 0, "label": "crab", "confidence": 0.9,
             "box": [x, 100.0, x + 40.0, 130.0], "v": 2}]


def _feed(obs: Observer, mono0_ns: int, wall0_ns: int, pairs: int, boxed: bool,
          got: Observations) -> None:
    for i in range(pairs):
        out = obs.feed(mono0_ns + i * PERIOD_NS, _box(100.0 + i) if boxed else [],
                       wall0_ns + i * PERIOD_NS)
        got.tracks += out.tracks
        got.counts += out.counts
        got.news += out.news


def test_tracks_and_news_survive_a_cut_on_a_restarted_clock(tmp_path: Path) -> None:
    cfg = ObserveConfig(interval_s=60.0, max_gap_s=1.0)
    obs = Observer(cfg)
    got = Observations()
    _feed(obs, 7_000 * 10**9, WALL0_NS, 30, True, got)  # a crab, then a short one ended
    _feed(obs, 7_003 * 10**9, WALL0_NS + 3 * 10**9, 15, False, got)
    _feed(obs, 7_005 * 10**9, WALL0_NS + 5 * 10**9, 20, True, got)  # a second crab, alive
    assert len(got.tracks) == 1 and [n for n in got.news if "new_label" in n]
    assert obs.tracker.alive == 1
    assert checkpoint.save(tmp_path, {"mono": obs})
    # The cut: a reboot, the monotonic clock starts again; 4 s of wall clock went by.
    (restored,) = checkpoint.load(tmp_path).values()
    after = Observations()
    _feed(restored, 20 * 10**9, WALL0_NS + 11 * 10**9, 30, True, after)
    end = restored.finish()
    tracks = [t["track"] for t in after.tracks + end.tracks]
    # The crab alive at the cut ended (4 s off > max_gap_s) with its own times; a new one
    # followed. Ids go on from before the cut.
    assert [t["id"] for t in tracks] == [2, 3]
    assert tracks[0]["first_s"] == round((WALL0_NS + 5 * 10**9) / 1e9, 3)
    assert tracks[0]["duration_s"] == 1.9
    assert not [n for n in after.news + end.news if "new_label" in n]  # crab is not news
    # The open interval went on: its pairs before and after the cut are in one line.
    counts = [c["counts"] for c in got.counts + after.counts + end.counts]
    assert sum(c["pairs"] for c in counts) == 95 and len(counts) == 1


def test_a_damaged_state_is_set_aside(tmp_path: Path) -> None:
    (tmp_path / checkpoint.STATE_FILE).write_bytes(b"not a pickle")
    assert checkpoint.load(tmp_path) == {}
    assert (tmp_path / (checkpoint.STATE_FILE + ".unreadable")).exists()
