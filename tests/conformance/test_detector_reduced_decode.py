"""A JPEG decoded at a reduced DCT scale gives the detector the detections of a full decode.

The kit's YOLOv8n (640x640 input) on its real photos, decoded as a worker decodes a JPEG
pair for the detector (trapflow.pools.pair_path.decode_pair: the largest DCT reduction that still
covers the letterboxed image) against the full decode of the same bytes. zidane.jpg
(1280x720, letterboxed to 640x360) is decoded at 1/2; bus.jpg (810x1080, letterboxed to
480x640) is less than twice that and is decoded whole, so its detections are identical.

Tolerance (stated, not the 1 px / 0.005 of the conformance tests, which compare the same
pixels): the reduced decode differs from a full decode plus the letterbox's own 2x resize by
0.3 grey levels on average (p99 2), and the int8 model moves with it. Every detection scoring
at least MARGIN above the confidence threshold in either decode has one in the other with
the same label, IoU >= 0.95 and confidence within 0.02; detections within MARGIN of the
threshold may come or go. Measured on zidane.jpg: the three detections within 9.1 px (boxes
90-1000 px wide, IoU >= 0.987), confidences within 0.011, and one extra person at 0.252.
A whole run with `--encoding jpeg` (capture encodes, the worker decodes at 1/2) meets the
same bound against the kit's reference detections.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from trapflow_workers.crab_detector import CrabDetector

from tests import builders
from tests.conformance.conftest import kit_path
from tests.conformance.detections import Det, assert_same
from trapflow.calibration.camera import StereoRig
from trapflow.plugin import Pair
from trapflow.pools.pair_path import process_pair
from trapflow.testing.kit import make_context
from trapflow.wire import jpeg
from trapflow.wire.messages import MonoIR

KIT = "04_onnx_detectors"
PARAMS = {"confidence": 0.25, "iou": 0.7, "max_detections": 300, "providers": ["cpu"]}
MARGIN, IOU_MIN, SCORE_TOL = 0.05, 0.95, 0.02


def _iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    area = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / area


def _matched(dets: list[Det], others: list[Det], what: str) -> None:
    """Each of `dets` clear of the threshold has its counterpart in `others`."""
    for label, score, box in dets:
        if score < PARAMS["confidence"] + MARGIN:  # type: ignore[operator]
            continue
        best = max((o for o in others if o[0] == label), default=None,
                   key=lambda o: _iou(box, o[2]))
        assert best is not None, f"{what}: no {label} for {label} {score:.3f} {box}"
        assert _iou(box, best[2]) >= IOU_MIN, f"{what}: {label} {box} vs {best[2]}"
        assert abs(best[1] - score) <= SCORE_TOL, f"{what}: {label} {score:.4f} vs {best[1]:.4f}"


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("image", "reduction"), [("zidane.jpg", 2), ("bus.jpg", 1)])
def test_reduced_decode_gives_the_full_decodes_detections(realdata: Path, image: str,
                                                          reduction: int) -> None:
    model = kit_path(realdata, KIT, "ultralytics_yolov8n_int8", "yolov8n_int8.onnx")
    data = kit_path(realdata, KIT, "images", image).read_bytes()
    whole = jpeg.decode(data)
    assert whole is not None
    h, w = whole.shape[:2]
    header = builders.pair_header(0, w, h, "jpeg")
    det = CrabDetector()
    rig = StereoRig.from_fov(w, h, 70.0, 0.12)
    det.configure({"model": str(model), **PARAMS}, make_context(rig, pool="mono"))
    # as a worker runs the detector's job: decoded at the reduction, boxes back in the frame's
    done = process_pair(det, header, data, data, pool="mono", worker="mono:0", calib="")
    pair = done.pair
    assert pair.reduction == reduction
    assert pair.left.shape[:2] == (-(-h // reduction), -(-w // reduction))
    assert isinstance(done.result.body, MonoIR)
    got = [(d.label, d.confidence, d.box) for d in done.result.body.detections]
    full = Pair(header=header, left=whole, right=whole)
    want = [(d.label, d.confidence, d.box) for d in det.process(full).detections]
    assert len(want) >= 3, f"{image}: the full decode found only {want}"
    if reduction == 1:
        assert_same(got, want, f"{image} decoded whole both times")
        return
    _matched(want, got, f"{image}: full decode -> 1/{reduction}")
    _matched(got, want, f"{image}: 1/{reduction} -> full decode")
    for _, _, box in got:  # in frame pixels, inside the frame
        assert 0 <= box[0] < box[2] <= w and 0 <= box[1] < box[3] <= h


@pytest.mark.timeout(120)
def test_jpeg_run_decodes_for_the_detector_and_reports_frame_pixels(
    realdata: Path, spawn, run_dir: Path
) -> None:
    """`trapflow start --encoding jpeg` on zidane.jpg: capture encodes the decoded photo
    (quality 90), the mono worker decodes that JPEG at 1/2 for YOLOv8n's 640x640 input, and
    results.jsonl holds the kit's reference detections within the tolerance above (boxes in
    frame pixels: the reduction is undone)."""
    import json

    from tests.conftest import write_config

    model = kit_path(realdata, KIT, "ultralytics_yolov8n_int8", "yolov8n_int8.onnx")
    photo = kit_path(realdata, KIT, "images", "zidane.jpg")
    ref = kit_path(realdata, KIT, "ultralytics_yolov8n_int8", "reference_detections.json")
    folder = run_dir.parent / "pairs"
    for side in ("left", "right"):
        (folder / side).mkdir(parents=True)
        (folder / side / "000000.jpg").symlink_to(photo)
    params = {"model": str(model), "confidence": 0.25, "iou": 0.7, "max_detections": 300}
    cfg = write_config(run_dir.parent / "detector.yaml", {"pools": {"mono": {"params": params}}})
    p = spawn(["--config", str(cfg), "--workers", "mono=1", "--encoding", "jpeg",
               "--source", f"images:{folder}"], run_dir)
    code, _, err = p.wait(90)
    assert code == 0, err
    got: list[Det] = [(b["label"], b["confidence"], tuple(b["box"]))
                      for row in p.results() for b in row.values()]
    entry = next(e for e in json.loads(ref.read_text()) if e["image"] == "zidane.jpg")
    want: list[Det] = [(d["name"], d["score"], tuple(d["xyxy"])) for d in entry["detections"]]
    assert "decoded to cover 640x360" in (run_dir / "trapflow.log").read_text()
    _matched(want, got, "reference -> jpeg run")
    _matched(got, want, "jpeg run -> reference")
