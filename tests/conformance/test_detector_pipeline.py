"""Detector conformance through a whole run: `trapflow start` on a real photo from the kit.

The kit's YOLOv8n, configured only through `pools.mono.params` in a user's YAML, with
the photo read by the images source, decoded at capture, carried through the ring and
the broker to a mono worker and written by the normalizer: results.jsonl holds the kit's
reference detections, within 1 px and 0.005 confidence.

Run with the default configuration and with `--encoding raw` spelled out: both must give
the reference. Regression: with `encoding: jpeg` as the default, capture re-encoded the
decoded photo (quality 90) and the worker saw a second JPEG generation, which moved a box
by 8 px; the ring now holds the frames decoded once at capture by default.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.conformance.conftest import kit_path
from tests.conformance.detections import Det, assert_same
from tests.conftest import Pipeline, write_config

KIT = "04_onnx_detectors"
IMAGE = "zidane.jpg"


@pytest.mark.timeout(120)
@pytest.mark.parametrize("extra", [[], ["--encoding", "raw"]], ids=["default", "raw"])
def test_run_writes_the_reference_detections(realdata: Path, spawn, run_dir: Path,
                                             extra: list[str]) -> None:
    model = kit_path(realdata, KIT, "ultralytics_yolov8n_int8", "yolov8n_int8.onnx")
    photo = kit_path(realdata, KIT, "images", IMAGE)
    ref = kit_path(realdata, KIT, "ultralytics_yolov8n_int8", "reference_detections.json")
    # A one-pair stereo folder whose both sides are the photo, linked in place.
    folder = run_dir.parent / "pairs"
    for side in ("left", "right"):
        (folder / side).mkdir(parents=True)
        (folder / side / "000000.jpg").symlink_to(photo)
    params = {"model": str(model), "confidence": 0.25, "iou": 0.7, "max_detections": 300}
    cfg = write_config(run_dir.parent / "detector.yaml", {"pools": {"mono": {"params": params}}})
    args = ["--config", str(cfg), "--workers", "mono=1", *extra]
    p: Pipeline = spawn([*args, "--source", f"images:{folder}"], run_dir)
    code, _, err = p.wait(90)
    assert code == 0, err
    got: list[Det] = []
    for row in p.results():
        ((key, body),) = row.items()
        assert key == "mono_ir", row
        got.append((body["label"], body["confidence"], tuple(body["box"])))
    entry = next(e for e in json.loads(ref.read_text()) if e["image"] == IMAGE)
    want: list[Det] = [(d["name"], d["score"], tuple(d["xyxy"])) for d in entry["detections"]]
    got.sort(key=lambda d: -d[1])
    assert_same(got, want, f"results.jsonl of a run on {IMAGE}")
