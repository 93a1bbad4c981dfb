"""Photo-trap events inside a pipeline: a trigger keeps the pairs around it on disk."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from tests.builders import small_source
from tests.conftest import Pipeline, only_pools, write_config

pytestmark = pytest.mark.slow  # starts whole pipelines


@pytest.mark.timeout(90)
def test_trigger_keeps_preroll_and_postroll_pairs(spawn, run_dir: Path) -> None:
    cfg = write_config(run_dir.parent / "events.yaml", {
        "source": small_source(10.0),
        "pools": only_pools({"stereo": {"plugin": "histogram", "policy": "latest",
                                        "gate": "always"}}),
        "events": {"enabled": True, "pre_s": 1.0, "post_s": 1.0,
                   "triggers": [{"algorithm": "stereo_ir", "not_label": "nothing"}]},
    })
    p: Pipeline = spawn(["--config", str(cfg), "--duration", "7"], run_dir)
    code, _, err = p.wait(60)
    assert code == 0, err
    events = sorted(d for d in (run_dir / "events").iterdir() if d.is_dir())
    assert events, "no event folder written"
    ev = events[0]  # the first (its pre- and post-roll whole; one at the stop may be cut)
    info = json.loads((ev / "event.json").read_text())
    lefts = sorted((ev / "left").glob("*.jpg"))
    rights = sorted((ev / "right").glob("*.jpg"))
    seen = {d.name: (json.loads((d / "event.json").read_text()) if (d / "event.json").exists()
                     else None) for d in events}
    assert info["pairs"] == len(lefts) == len(rights) >= 10, (len(lefts), len(rights), seen)
    assert [f.name for f in lefts] == [f.name for f in rights]
    assert cv2.imread(str(lefts[0])).shape == (240, 320, 3)
    assert info["results"] >= 1 and (ev / "results.jsonl").read_text().count("stereo_ir") >= 1
    seqs = [int(f.stem) for f in lefts]
    assert seqs == sorted(set(seqs))  # no pair written twice
