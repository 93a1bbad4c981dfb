"""`trapflow dataset synth` writes MOTChallenge ground truth (gt/gt.txt, seqinfo.ini) that
the tracker's MOT reader takes, with the animals' ids from the truth."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from trapflow.cli.dataset import dataset
from trapflow.synth.dataset import mot_gt_lines
from trapflow.tracking.motformat import read_fps, read_mot
from trapflow.wire.messages import Truth, TruthObject

GT_LINES = [
    # (objects, lines)
    # A crab: class 1 (classes.txt order from 1), visibility = 1 - occluded.
    ([TruthObject(label="crab", box=(10, 20, 40, 60), id=7, occluded=0.25)],
     ["3,7,10.00,20.00,30.00,40.00,1,1,0.750"]),
    # A tag is left out (its id is the AprilTag's), a scallop kept as class 2.
    ([TruthObject(label="tag", box=(0, 0, 20, 20), id=1),
      TruthObject(label="scallop", box=(50, 50, 60, 58), id=2)],
     ["3,2,50.00,50.00,10.00,8.00,1,2,1.000"]),
    # Too hidden to be labelled: no line, as no YOLO label.
    ([TruthObject(label="crab", box=(10, 20, 40, 60), id=7, occluded=0.9)], []),
]


@pytest.mark.parametrize(("objects", "lines"), GT_LINES)
def test_gt_lines(objects: list[TruthObject], lines: list[str]) -> None:
    truth = Truth(seq=2, pose=(1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0), objects=objects)
    assert mot_gt_lines(truth, 3) == lines


def test_dataset_writes_gt_and_seqinfo(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    res = CliRunner().invoke(dataset, ["synth", str(out), "--frames", "30", "--seed", "3",
                                       "--width", "160", "--height", "96", "--rate", "10",
                                       "-o", "density=5", "-o", "empty_fraction=0"])
    assert res.exit_code == 0, res.output
    gt = read_mot(out / "gt" / "gt.txt")
    assert read_fps(out / "gt" / "gt.txt") == 10.0
    truths = [json.loads(line) for line in (out / "truth.jsonl").read_text().splitlines()]
    assert gt, "expected animals in 30 pairs of a dense world"
    for row in gt:
        ids = [o["id"] for o in truths[row.frame - 1]["objects"]]
        assert row.id in ids
