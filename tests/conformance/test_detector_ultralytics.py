"""Detector conformance, Ultralytics layout: a real YOLOv8n on two real photos from the kit.

trapflow's mono detector must give the detections of Ultralytics' own processing
(centred LetterBox, RGB, /255, conf 0.25, per-class NMS at IoU 0.7, max 300 boxes,
scale_boxes) within 1 px and 0.005 confidence: against the kit's reference outputs and
against the same processing written again here, independently of trapflow's code.
"""

from __future__ import annotations

import ast
import json
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
import pytest

from tests.conformance.conftest import kit_path
from tests.conformance.detections import Det, assert_same, trapflow_detections

KIT = "04_onnx_detectors"
IMAGES = ["bus.jpg", "zidane.jpg"]
CONF, IOU, MAX_DET = 0.25, 0.7, 300  # Ultralytics' predict defaults
PARAMS = {"confidence": CONF, "iou": IOU, "max_detections": MAX_DET}


@pytest.fixture
def model(realdata: Path) -> Path:
    return kit_path(realdata, KIT, "ultralytics_yolov8n_int8", "yolov8n_int8.onnx")


def _names(session: ort.InferenceSession) -> dict[int, str]:
    meta = session.get_modelmeta().custom_metadata_map
    return {int(k): str(v) for k, v in ast.literal_eval(meta["names"]).items()}


def ultralytics_reference(model: Path, image: np.ndarray) -> list[Det]:
    """Ultralytics' predict path for a [1, 4+nc, N] ONNX export, written for this test."""
    session = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    inp = session.get_inputs()[0]
    in_h, in_w = int(inp.shape[2]), int(inp.shape[3])
    h0, w0 = image.shape[:2]
    # LetterBox(new_shape, auto=False, scaleup=True, center=True)
    gain = min(in_h / h0, in_w / w0)
    new_w, new_h = int(round(w0 * gain)), int(round(h0 * gain))
    half_w, half_h = (in_w - new_w) / 2, (in_h - new_h) / 2
    top, left = int(round(half_h - 0.1)), int(round(half_w - 0.1))
    bottom, right = int(round(half_h + 0.1)), int(round(half_w + 0.1))
    resized = cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    canvas = cv2.copyMakeBorder(
        resized, top, bottom, left, right, cv2.BORDER_CONSTANT, value=(114, 114, 114)
    )
    assert canvas.shape[:2] == (in_h, in_w)
    # BGR -> RGB, HWC -> CHW, float32, /255
    x = np.ascontiguousarray(canvas[..., ::-1].transpose(2, 0, 1)).astype(np.float32)
    x /= 255.0
    pred = session.run(None, {inp.name: x[None]})[0][0]  # [4+nc, N]
    # non_max_suppression: candidates by best class score, class offset, torchvision nms
    cls_scores = pred[4:]
    best = cls_scores.max(axis=0)
    cand = np.flatnonzero(best > CONF)
    cx, cy, w, h = pred[:4, cand]
    xyxy = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1).astype(np.float64)
    cls = cls_scores[:, cand].argmax(axis=0)
    conf = best[cand]
    offset = xyxy + cls[:, None] * 7680.0
    keep = _greedy_nms(offset, conf, IOU)[:MAX_DET]
    # scale_boxes: padding from the gain, then /gain, clipped to the image
    pad_x = round((in_w - w0 * gain) / 2 - 0.1)
    pad_y = round((in_h - h0 * gain) / 2 - 0.1)
    boxes = (xyxy[keep] - [pad_x, pad_y, pad_x, pad_y]) / gain
    boxes[:, 0::2] = boxes[:, 0::2].clip(0, w0)
    boxes[:, 1::2] = boxes[:, 1::2].clip(0, h0)
    names = _names(session)
    return [
        (names[int(c)], float(s), (b[0], b[1], b[2], b[3]))
        for b, s, c in zip(boxes.tolist(), conf[keep], cls[keep], strict=True)
    ]


def _greedy_nms(boxes: np.ndarray, scores: np.ndarray, thr: float) -> list[int]:
    """torchvision.ops.nms: highest score first, drop boxes with IoU above thr."""
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    alive = np.ones(len(scores), bool)
    keep = []
    for i in np.argsort(-scores, kind="stable"):
        if not alive[i]:
            continue
        keep.append(int(i))
        lt = np.maximum(boxes[i, :2], boxes[:, :2])
        rb = np.minimum(boxes[i, 2:], boxes[:, 2:])
        inter = np.prod(np.clip(rb - lt, 0, None), axis=1)
        iou = inter / (area[i] + area - inter)
        alive &= iou <= thr
    return keep


def kit_reference(root: Path, image: str) -> list[Det]:
    path = kit_path(root, KIT, "ultralytics_yolov8n_int8", "reference_detections.json")
    entry = next(e for e in json.loads(path.read_text()) if e["image"] == image)
    return [(d["name"], d["score"], tuple(d["xyxy"])) for d in entry["detections"]]


@pytest.mark.parametrize("name", IMAGES)
def test_yolov8_detections_equal_the_kit_reference(realdata: Path, model: Path, name: str) -> None:
    image = cv2.imread(str(kit_path(realdata, KIT, "images", name)), cv2.IMREAD_COLOR)
    got = trapflow_detections(model, image, **PARAMS)
    want = kit_reference(realdata, name)
    assert_same(got, want, f"{name} vs the kit's reference_detections.json")


@pytest.mark.parametrize("name", IMAGES)
def test_yolov8_detections_equal_ultralytics_processing(
    realdata: Path, model: Path, name: str
) -> None:
    image = cv2.imread(str(kit_path(realdata, KIT, "images", name)), cv2.IMREAD_COLOR)
    want = ultralytics_reference(model, image)
    # The reference written here agrees with the kit's before it judges trapflow.
    assert_same(want, kit_reference(realdata, name), f"{name}: this test's reference vs kit")
    got = trapflow_detections(model, image, **PARAMS)
    assert_same(got, want, f"{name} vs Ultralytics' processing")
