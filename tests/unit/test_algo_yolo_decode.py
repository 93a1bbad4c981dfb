"""Letterbox, layout detection, decoders and NMS of the YOLO post-processing (pure numpy)."""

from __future__ import annotations

import numpy as np
import pytest
from trapflow_workers.testkit_onnx import yolo_tensor
from trapflow_workers.yolo_decode import (
    check_layout,
    decode,
    detect_layout,
    grid_size,
    letterbox,
    nms,
)

from trapflow.errors import WorkerError

BOXES = [(40.0, 60.0, 120.0, 140.0), (200.0, 30.0, 260.0, 90.0)]


@pytest.mark.parametrize(
    ("shape", "out_hw"),
    [((480, 640), (320, 320)), ((720, 1280), (384, 640)), ((300, 200), (320, 320))],
)
def test_letterbox_maps_boxes_back(shape: tuple[int, int], out_hw: tuple[int, int]) -> None:
    img = np.zeros((*shape, 3), np.uint8)
    img[50:100, 30:90] = 255
    boxed, lb = letterbox(img, out_hw)
    assert boxed.shape[:2] == out_hw
    ys, xs = np.nonzero(boxed[:, :, 0] > 200)
    found = np.array([[xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]], float)
    back = lb.to_image(found, shape[1], shape[0])[0]
    np.testing.assert_allclose(back, [30, 50, 90, 100], atol=1.0 / lb.scale + 0.5)
    # padding is grey 114 where the image is not
    assert boxed[0, 0, 0] == 114 or lb.pad_y == 0


@pytest.mark.parametrize("layout", ["yolov8", "yolov5", "yolox"])
def test_decoders_recover_boxes(layout: str) -> None:
    hw = (320, 320)
    out = yolo_tensor(layout, BOXES, [0, 2], [0.9, 0.8], nc=3, input_hw=hw, n=500)  # type: ignore[arg-type]
    assert detect_layout(out.shape, hw, nc=3) == layout
    assert detect_layout(out.shape, hw, nc=None) == layout
    boxes, scores, ids = decode(out, layout, 0.25, hw)  # type: ignore[arg-type]
    order = np.argsort(-scores)
    np.testing.assert_allclose(boxes[order], BOXES, atol=1e-3)
    np.testing.assert_allclose(scores[order], [0.9, 0.8], atol=1e-5)
    assert ids[order].tolist() == [0, 2]


@pytest.mark.parametrize(
    ("shape", "nc", "error"),
    [
        ((1, 84), None, "expected"),
        ((2, 84, 8400), 80, "expected"),
        ((1, 84, 8400), 3, "matches no decoder for 3 classes"),
        ((1, 4, 3), None, "matches no decoder"),
        ((1, 1, 1, 8400), None, "expected"),
    ],
)
def test_detect_layout_rejects(shape: tuple[int, ...], nc: int | None, error: str) -> None:
    with pytest.raises(WorkerError, match=error):
        detect_layout(shape, (640, 640), nc)


def test_check_layout_yolox_needs_grid() -> None:
    with pytest.raises(WorkerError, match="expected N=2100"):
        check_layout("yolox", (1, 100, 8), (320, 320))
    assert check_layout("yolox", (1, grid_size((320, 320)), 8), (320, 320)) == 3


def test_nms_is_class_aware() -> None:
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [0, 0, 10, 10], [50, 50, 60, 60]], float)
    scores = np.array([0.9, 0.8, 0.7, 0.6])
    ids = np.array([0, 0, 1, 0])
    assert nms(boxes, scores, ids, iou=0.5).tolist() == [0, 2, 3]
    assert nms(boxes, scores, ids, iou=0.5, max_det=2).tolist() == [0, 2]
    assert nms(boxes, scores, np.zeros(4, int), iou=0.5).tolist() == [0, 3]
    assert nms(boxes[:0], scores[:0], ids[:0], iou=0.5).size == 0


def test_confidence_threshold_filters() -> None:
    out = yolo_tensor("yolov8", BOXES, [0, 1], [0.9, 0.2], nc=2, input_hw=(320, 320), n=50)
    _, scores, _ = decode(out, "yolov8", 0.25, (320, 320))
    assert scores.tolist() == pytest.approx([0.9])
