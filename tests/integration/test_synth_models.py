"""The committed demo models still work on held-out scenes rendered with a fresh seed,
both on their own and through the runtime plugins that load them (metadata included)."""

from __future__ import annotations

import sys
from functools import cache
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # renders and runs the algorithms over long sequences

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "workers" / "models"
sys.path.insert(0, str(ROOT / "scripts"))
import synth_demo_data as sd  # noqa: E402

ort = pytest.importorskip("onnxruntime")
from trapflow_workers.crab_detector import CrabDetector  # noqa: E402
from trapflow_workers.scene_classifier import SceneClassifier  # noqa: E402

from trapflow.testing.kit import make_context, make_pair  # noqa: E402

HELD_OUT_SEEDS = [777_001, 777_002, 777_004]  # never used in training (1000+) or cards (9000+)


@cache
def _held_out() -> tuple[tuple[np.ndarray, np.ndarray, object], ...]:
    """Rendered once per session, shared by the tests (rendering is most of their time)."""
    return tuple(sd.samples(HELD_OUT_SEEDS, 30))


@pytest.mark.timeout(90)
def test_detector_reaches_map_on_held_out_scenes() -> None:
    det = ort.InferenceSession(str(MODELS / "crab_detector.onnx"),
                               providers=["CPUExecutionProvider"])
    assert det.get_outputs()[0].shape[1] == 4 + len(sd.DET_CLASSES)  # YOLOv8 [1, 4+nc, N]
    assert (MODELS / "crab_detector.labels").read_text().split() == list(sd.DET_CLASSES)
    dets: list[tuple[int, float, np.ndarray]] = []
    gts: list[list[np.ndarray]] = []
    for img, (left, _right, truth) in enumerate(_held_out()):
        x, s, dx, dy = sd.det_input(left)
        out = det.run(None, {"images": x})[0]
        gts.append([np.array(t[1:]) for t in sd.det_targets(truth, s, dx, dy) if t[0] == 0])
        dets += [(img, score, box) for c, score, box in sd.decode(out) if c == 0]
    assert sum(len(g) for g in gts) >= 10, "held-out set has too few crabs to judge"
    ap = sd.average_precision(dets, gts)
    assert ap >= 0.7, f"crab mAP@0.5 {ap:.3f} on held-out scenes, expected >= 0.7"


@pytest.mark.timeout(90)
@pytest.mark.parametrize("variant", ["fp32", "int8"])
def test_crab_detector_plugin_finds_held_out_crabs(variant: str) -> None:
    """CrabDetector with its defaults (packaged model, labels from metadata) on full frames;
    the int8 variant (scripts/quantize_detector.py) to the same bounds."""
    det = CrabDetector()
    det.configure({"providers": ["cpu"], "variant": variant}, make_context())
    found = total = false_pos = 0
    for seq, (left, right, truth) in enumerate(_held_out()):
        got = det.process(make_pair(left, right, seq=seq))
        assert {d.label for d in got.detections} <= set(sd.DET_CLASSES)
        boxes = [np.array(d.box) for d in got.detections if d.label == "crab"]
        want = [np.array(t[1:]) for t in sd.det_targets(truth, 1.0, 0, 0) if t[0] == 0]
        total += len(want)
        if boxes and want:
            ious = sd.iou(np.array(want), np.array(boxes))
            found += int((ious.max(1) >= 0.5).sum())
            false_pos += int((ious.max(0) < 0.5).sum())
        else:
            false_pos += len(boxes)
    assert total >= 10, "held-out set has too few crabs to judge"
    assert found / total >= 0.6, f"plugin found {found} of {total} crabs at IoU >= 0.5"
    assert false_pos <= total, f"{false_pos} crab boxes match no crab ({total} crabs)"


@pytest.mark.timeout(90)
def test_scene_classifier_plugin_reaches_accuracy_on_held_out_scenes() -> None:
    """SceneClassifier with its defaults: packaged model, arrangement and labels from metadata."""
    clf = SceneClassifier()
    clf.configure({"providers": ["cpu"], "threshold": 0.0}, make_context())
    assert clf.arrangement == "concat_channels"
    assert clf.labels == list(sd.CLS_LABELS)
    assert (MODELS / "scene_classifier.labels").read_text().split() == list(sd.CLS_LABELS)
    confusion = np.zeros((len(sd.CLS_LABELS),) * 2, int)
    for seq, (left, right, truth) in enumerate(_held_out()):
        got = clf.process(make_pair(left, right, seq=seq))
        confusion[sd.CLS_LABELS.index(truth.scene_label), sd.CLS_LABELS.index(got.label)] += 1
    assert (confusion.sum(1) > 0).sum() >= 2, f"held-out set has too few kinds: {confusion}"
    acc = np.trace(confusion) / confusion.sum()
    assert acc >= 0.85, f"scene accuracy {acc:.3f} held out, expected >= 0.85: {confusion}"
