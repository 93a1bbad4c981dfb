"""Detector conformance, YOLOv5 layout: a tiny YOLOv5-shaped model on the kit's real photos.

The reference is YOLOv5's detect.py path for an ONNX export written again here:
`letterbox(auto=False)` (size rounded, padding split round(d -/+ 0.1), grey 114),
BGR -> RGB, /255; `non_max_suppression` (objectness > conf, conf = obj * cls, best class
> conf, per-class NMS by a 7680 px class offset, IoU 0.45, max_det 1000); `scale_boxes`
(minus the padding, / gain, clipped to the image).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conformance.conftest import kit_path
from tests.conformance.detections import Det, assert_same, differ, trapflow_detections

onnx = pytest.importorskip("onnx", reason="building the tiny YOLOv5 model needs onnx")
import onnxruntime as ort  # noqa: E402
from trapflow_workers.crab_detector import CrabDetector  # noqa: E402

from tests.conformance.tiny_yolo import yolov5_model  # noqa: E402
from trapflow.testing.kit import make_context  # noqa: E402

KIT = "04_onnx_detectors"
IMAGES = ["bus.jpg", "zidane.jpg"]
INPUT_HW = (640, 640)  # detect.py's default --imgsz
NC = 80
NAMES = [f"species{i}" for i in range(NC)]
CONF, IOU, MAX_DET = 0.25, 0.45, 1000  # detect.py's defaults
PARAMS = {"confidence": CONF, "iou": IOU, "max_detections": MAX_DET}


def yolov5_letterbox(im: np.ndarray, new_shape: tuple[int, int]) -> np.ndarray:
    """utils/augmentations.py letterbox(auto=False, scaleFill=False, scaleup=True)."""
    shape = im.shape[:2]
    r = min(new_shape[0] / shape[0], new_shape[1] / shape[1])
    new_unpad = int(round(shape[1] * r)), int(round(shape[0] * r))
    dw, dh = (new_shape[1] - new_unpad[0]) / 2, (new_shape[0] - new_unpad[1]) / 2
    if shape[::-1] != new_unpad:
        im = cv2.resize(im, new_unpad, interpolation=cv2.INTER_LINEAR)
    top, bottom = int(round(dh - 0.1)), int(round(dh + 0.1))
    left, right = int(round(dw - 0.1)), int(round(dw + 0.1))
    return cv2.copyMakeBorder(
        im, top, bottom, left, right, cv2.BORDER_CONSTANT, value=(114, 114, 114)
    )


def _torchvision_nms(boxes: np.ndarray, scores: np.ndarray, thr: float) -> list[int]:
    order = list(np.argsort(-scores, kind="stable"))
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    keep: list[int] = []
    while order:
        i = int(order.pop(0))
        keep.append(i)
        rest = np.array(order, dtype=int)
        if not rest.size:
            break
        lt = np.maximum(boxes[i, :2], boxes[rest, :2])
        rb = np.minimum(boxes[i, 2:], boxes[rest, 2:])
        inter = np.prod(np.clip(rb - lt, 0, None), axis=1)
        iou = inter / (area[i] + area[rest] - inter)
        order = [int(j) for j in rest[iou <= thr]]
    return keep


def yolov5_reference(model: Path, im0: np.ndarray) -> list[Det]:
    session = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    im = yolov5_letterbox(im0, INPUT_HW)
    im = np.ascontiguousarray(im.transpose((2, 0, 1))[::-1])  # HWC to CHW, BGR to RGB
    x = im.astype(np.float32)
    x /= 255
    pred = session.run(None, {session.get_inputs()[0].name: x[None]})[0][0]  # [N, 5+nc]
    # non_max_suppression(conf_thres, iou_thres, agnostic=False, multi_label=False)
    cand = pred[pred[:, 4] > CONF].copy()
    cand[:, 5:] *= cand[:, 4:5]
    cx, cy, w, h = cand[:, 0], cand[:, 1], cand[:, 2], cand[:, 3]
    box = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
    j = cand[:, 5:].argmax(1)
    conf = cand[np.arange(len(j)), 5 + j]
    sel = conf > CONF
    box, conf, j = box[sel], conf[sel], j[sel]
    keep = _torchvision_nms(box + j[:, None] * 7680.0, conf, IOU)[:MAX_DET]
    # scale_boxes(img1_shape, boxes, img0_shape): YOLOv5 takes the padding unrounded
    gain = min(INPUT_HW[0] / im0.shape[0], INPUT_HW[1] / im0.shape[1])
    pad = (INPUT_HW[1] - im0.shape[1] * gain) / 2, (INPUT_HW[0] - im0.shape[0] * gain) / 2
    out = box[keep].astype(np.float64)
    out[:, [0, 2]] -= pad[0]
    out[:, [1, 3]] -= pad[1]
    out /= gain
    out[:, [0, 2]] = out[:, [0, 2]].clip(0, im0.shape[1])
    out[:, [1, 3]] = out[:, [1, 3]].clip(0, im0.shape[0])
    return [
        (NAMES[int(c)], float(s), (b[0], b[1], b[2], b[3]))
        for b, s, c in zip(out.tolist(), conf[keep], j[keep], strict=True)
    ]


@pytest.fixture
def tiny_yolov5(tmp_path: Path) -> Path:
    return yolov5_model(tmp_path / "yolov5.onnx", INPUT_HW, NC, NAMES)


def _image(realdata: Path, name: str) -> np.ndarray:
    return cv2.imread(str(kit_path(realdata, KIT, "images", name)), cv2.IMREAD_COLOR)


@pytest.mark.parametrize("name", IMAGES)
def test_yolov5_detections_equal_yolov5_processing(
    realdata: Path, tiny_yolov5: Path, name: str
) -> None:
    image = _image(realdata, name)
    want = yolov5_reference(tiny_yolov5, image)
    assert len(want) >= 5, "the tiny model must detect something for the test to mean anything"
    det = CrabDetector()
    det.configure({"model": str(tiny_yolov5)}, make_context(pool="mono"))
    assert det.layout == "yolov5"
    got = trapflow_detections(tiny_yolov5, image, **PARAMS)
    assert_same(got, want, f"{name}, YOLOv5 export")
    # The placement matters: the top-left one of YOLOX gives other detections.
    assert differ(trapflow_detections(tiny_yolov5, image, letterbox="topleft", **PARAMS), want)
