"""Observations in a real run: a synthetic dataset (seed 4244, crabs, not used in
development) read back through `images:`, the detector's lines tracked by the normalizer,
tracks.jsonl and counts.jsonl written, MaxN against the dataset's own MOT ground truth."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.conftest import REPO, Pipeline, write_config

pytestmark = pytest.mark.slow  # starts whole pipelines

SEED = 4244  # crabs walk through; never used to tune the tracker
FRAMES = 150


def _truth_max_n(gt: Path, classes: list[str]) -> dict[str, int]:
    per_frame: Counter[tuple[int, str]] = Counter()
    for line in gt.read_text().splitlines():
        f = line.split(",")
        per_frame[(int(f[0]), classes[int(f[7]) - 1])] += 1
    out: dict[str, int] = {}
    for (_frame, label), n in per_frame.items():
        out[label] = max(out.get(label, 0), n)
    return out


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_run_tracks_counts_and_measures(tmp_path: Path, run_dir: Path,
                                          spawn: Callable[..., Pipeline]) -> None:
    data = tmp_path / "synth"
    subprocess.run([sys.executable, "-m", "trapflow", "dataset", "synth", str(data),
                    "--frames", str(FRAMES), "--seed", str(SEED), "--width", "640",
                    "--height", "360"], check=True, cwd=REPO, capture_output=True, timeout=120)
    # Every pair through the detector (a finite source waits for no one: fifo keeps them).
    cfg = write_config(tmp_path / "c.yaml", {
        "pools": {"mono": {"count": 1, "policy": "fifo:256"}, "stereo": {"count": 0},
                  "vo": {"count": 0}},
        "observe": {"interval_s": 3600}})
    p = spawn(["--config", str(cfg), "--source", f"images:{data}"], run_dir)
    code, _out, err = p.wait(200)
    assert code == 0, err

    lines = [json.loads(line)["mono_ir"] for line in
             (run_dir / "results.jsonl").read_text().splitlines()]
    boxes = [d for d in lines if d["label"] != "none"]
    assert boxes, "the detector found nothing"
    assert all("track" in d for d in boxes)  # every detection line says its track
    assert all(d["v"] == 2 and list(d)[-1] == "v" for d in lines)
    tracked = [d for d in boxes if d["track"] is not None]
    # Weak boxes (below observe.high, 0.5) only extend tracks, so clutter stays untracked;
    # confident boxes belong to tracks, but for each track's first one (null until confirmed).
    strong = [d for d in boxes if d["confidence"] >= 0.5]
    assert sum(d["track"] is not None for d in strong) >= 0.8 * len(strong)

    tracks = [json.loads(t)["track"] for t in
              (run_dir / "tracks.jsonl").read_text().splitlines()]
    assert tracks and {t["id"] for t in tracks} >= {d["track"] for d in tracked}
    for t in tracks:
        assert t["first_s"] <= t["last_s"] and t["pairs"] >= 2 and len(t["path"]) <= 32
        assert 0.5 <= t["label_share"] <= 1.0
    counts = [json.loads(c)["counts"] for c in
              (run_dir / "counts.jsonl").read_text().splitlines()]
    assert counts and sum(c["pairs"] for c in counts) == len({d["seq"] for d in lines})
    run_max_n: dict[str, int] = {}
    for c in counts:
        for lab in c["labels"]:
            run_max_n[lab["label"]] = max(run_max_n.get(lab["label"], 0), lab["max_n"])
    classes = (data / "classes.txt").read_text().split()
    truth = _truth_max_n(data / "gt" / "gt.txt", classes)
    assert truth, "the seed shows no animal"
    for label in set(truth) | set(run_max_n):
        assert abs(run_max_n.get(label, 0) - truth.get(label, 0)) <= 1, (run_max_n, truth)
    # The stereo rig measured the animals: ranges on the lines, a length per track.
    assert any("range_m" in d for d in boxes)
    assert any("length_m" in t for t in tracks)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_moving_rigs_tracks_take_vos_poses(tmp_path: Path, run_dir: Path,
                                              spawn: Callable[..., Pipeline]) -> None:
    """With a VO pool in the run, the normalizer hands VO's poses to the trackers: every
    track's speed is over the ground (the rig's own motion removed), none against the rig.
    Speed accuracy against the truth: scripts/bench_speed.py."""
    data = tmp_path / "synth"
    subprocess.run([sys.executable, "-m", "trapflow", "dataset", "synth", str(data),
                    "--frames", str(FRAMES), "--seed", str(SEED), "--moving", "--rate", "10",
                    "--width", "640", "--height", "360"],
                   check=True, cwd=REPO, capture_output=True, timeout=120)
    cfg = write_config(tmp_path / "c.yaml", {
        "pools": {"mono": {"count": 1, "policy": "fifo:256"}, "stereo": {"count": 0},
                  "vo": {"count": 1, "policy": "ordered:256"}},
        "observe": {"interval_s": 3600}})
    p = spawn(["--config", str(cfg), "--source", f"images:{data}"], run_dir)
    code, _out, err = p.wait(250)
    assert code == 0, err
    results = [json.loads(line) for line in (run_dir / "results.jsonl").read_text().splitlines()]
    vo = [r["stereo_vo"] for r in results if "stereo_vo" in r]
    assert sum("Rt" in r for r in vo) >= FRAMES // 2, "VO placed too few pairs"
    tracks = [json.loads(t)["track"] for t in
              (run_dir / "tracks.jsonl").read_text().splitlines()]
    with_speed = [t for t in tracks if "speed_m_s" in t]
    assert with_speed, tracks
    assert {t["speed_frame"] for t in with_speed} == {"ground"}
