"""`trapflow dataset synth`: KITTI layout, YOLO labels, refusal of non-empty folders, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from trapflow.cli.dataset import dataset

SMALL = ["--width", "160", "--height", "96"]


def test_writes_kitti_and_yolo(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    res = CliRunner().invoke(dataset, ["synth", str(out), "--frames", "4", "--seed", "2",
                                       "--moving", "-o", "tags=1", *SMALL])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (out / "image_0").iterdir()) == [f"{i:06d}.png" for i in range(4)]
    assert len(list((out / "image_1").iterdir())) == 4
    calib = dict(line.split(": ") for line in (out / "calib.txt").read_text().splitlines())
    p0 = np.array(calib["P0"].split(), float).reshape(3, 4)
    p1 = np.array(calib["P1"].split(), float).reshape(3, 4)
    assert p0[0, 3] == 0 and p1[0, 3] == pytest.approx(-p0[0, 0] * 0.12)
    poses = np.loadtxt(out / "poses.txt")
    assert poses.shape == (4, 12) and np.allclose(poses[0], np.eye(4)[:3].reshape(-1))
    assert np.loadtxt(out / "times.txt")[1] == pytest.approx(1 / 15)
    assert (out / "classes.txt").read_text().split() == ["crab", "scallop", "tag"]
    for lab in (out / "labels").iterdir():
        for line in lab.read_text().splitlines():
            cls, *vals = line.split()
            assert cls in ("0", "1", "2") and all(0.0 <= float(v) <= 1.0 for v in vals)


def test_refuses_non_empty_folder_unless_overwrite(tmp_path: Path) -> None:
    (tmp_path / "keep.txt").write_text("mine")
    args = ["synth", str(tmp_path), "--frames", "1", *SMALL]
    res = CliRunner().invoke(dataset, args)
    assert res.exit_code == 2 and "not empty" in res.output
    res = CliRunner().invoke(dataset, [*args, "--overwrite"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "keep.txt").read_text() == "mine"


@pytest.mark.parametrize(
    ("args", "error"),
    [
        (["--frames", "0"], "--frames"),
        (["--frames", "1", "--seed", "abc"], "--seed"),
        (["--frames", "1", "--seed", "-3"], "--seed"),
        (["--frames", "1", "--width", "8"], "--width"),
        (["--frames", "1", "--rate", "0"], "--rate"),
        (["--frames", "1", "-o", "density"], "KEY=VALUE"),
        (["--frames", "1", "-o", "fog=1"], "--option.fog"),
        (["--frames", "1", "-o", "snow=9"], "--option.snow"),
    ],
)
def test_bad_input_names_the_parameter(tmp_path: Path, args: list[str], error: str) -> None:
    res = CliRunner().invoke(dataset, ["synth", str(tmp_path / "x"), *SMALL, *args])
    assert res.exit_code == 2 and error in res.output, res.output


def test_the_default_seed_labels_animals(tmp_path: Path) -> None:
    """Regression (issue 22, item 9): `trapflow dataset synth` with its default seed wrote 0
    annotations (seed 0's first scene is empty for its first 20 s)."""
    out = tmp_path / "ds"
    res = CliRunner().invoke(dataset, ["synth", str(out), "--frames", "4",
                                                       "--width", "320", "--height", "240"])
    assert res.exit_code == 0, res.output
    coco = json.loads((out / "coco.json").read_text())
    assert len(coco["annotations"]) >= 3 and "warning" not in res.stderr
    assert sum(len(p.read_text().splitlines()) for p in (out / "labels").iterdir()) >= 3


def test_a_dataset_without_annotation_says_so(tmp_path: Path) -> None:
    """The other half of issue 22, item 9: an empty dataset is written, and said to be empty."""
    res = CliRunner().invoke(dataset, ["synth", str(tmp_path / "ds"), "--frames",
                                                       "2", "--seed", "0", *SMALL])
    assert res.exit_code == 0, res.output
    assert "no animal or tag was labelled in these 2 pairs (seed 0)" in res.stderr
