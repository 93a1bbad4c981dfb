"""Detector conformance, YOLOX layouts: tiny YOLOX-shaped models on the kit's real photos.

The reference is YOLOX's own ONNX path written again here (demo/ONNXRuntime/onnx_inference.py):
`preproc` (resize by r = min(H/h, W/w) with truncated size, image at the top-left of a
114-grey canvas, BGR, no scaling), `demo_postprocess` (grid + stride decode with exp for
w/h) when the export has no decode in the graph, score = obj * cls, boxes / r, and
`multiclass_nms` (class-agnostic by default, IoU 0.45 with +1 pixel edges, score > 0.1).
trapflow clips boxes to the image; the reference does so after NMS.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conformance.conftest import kit_path
from tests.conformance.detections import Det, assert_same, differ, trapflow_detections

onnx = pytest.importorskip("onnx", reason="building the tiny YOLOX models needs onnx")
import onnxruntime as ort  # noqa: E402
from trapflow_workers.crab_detector import CrabDetector  # noqa: E402

from tests.conformance.tiny_yolo import STRIDES, yolox_model  # noqa: E402
from trapflow.testing.kit import make_context  # noqa: E402

KIT = "04_onnx_detectors"
IMAGES = ["bus.jpg", "zidane.jpg"]
INPUT_HW = (416, 416)  # YOLOX-Nano / Tiny test size
NC = 80
NMS_THR, SCORE_THR = 0.45, 0.1  # the demo's multiclass_nms arguments
PARAMS = {"confidence": SCORE_THR, "iou": NMS_THR, "max_detections": 1000}


def yolox_preproc(img: np.ndarray, input_size: tuple[int, int]) -> tuple[np.ndarray, float]:
    """yolox/data/data_augment.py preproc: top-left placement, 114 padding, CHW float32."""
    padded = np.full((input_size[0], input_size[1], 3), 114, np.uint8)
    r = min(input_size[0] / img.shape[0], input_size[1] / img.shape[1])
    size = (int(img.shape[1] * r), int(img.shape[0] * r))
    resized = cv2.resize(img, size, interpolation=cv2.INTER_LINEAR).astype(np.uint8)
    padded[: size[1], : size[0]] = resized
    return np.ascontiguousarray(padded.transpose(2, 0, 1), dtype=np.float32), r


def demo_postprocess(outputs: np.ndarray, img_size: tuple[int, int]) -> np.ndarray:
    """yolox/utils/demo_utils.py demo_postprocess: grid offsets and log sizes to pixels."""
    grids, strides = [], []
    for s in STRIDES:
        xv, yv = np.meshgrid(np.arange(img_size[1] // s), np.arange(img_size[0] // s))
        grid = np.stack((xv, yv), 2).reshape(1, -1, 2)
        grids.append(grid)
        strides.append(np.full((*grid.shape[:2], 1), s))
    out = outputs.copy()
    out[..., :2] = (out[..., :2] + np.concatenate(grids, 1)) * np.concatenate(strides, 1)
    out[..., 2:4] = np.exp(out[..., 2:4]) * np.concatenate(strides, 1)
    return out


def nms_plus_one(boxes: np.ndarray, scores: np.ndarray, thr: float) -> list[int]:
    """demo_utils.nms: areas and overlaps counted with +1 pixel edges."""
    x1, y1, x2, y2 = boxes.T
    areas = (x2 - x1 + 1) * (y2 - y1 + 1)
    order = scores.argsort()[::-1]
    keep = []
    while order.size > 0:
        i = order[0]
        keep.append(int(i))
        w = np.maximum(0.0, np.minimum(x2[i], x2[order[1:]]) - np.maximum(x1[i], x1[order[1:]]) + 1)
        h = np.maximum(0.0, np.minimum(y2[i], y2[order[1:]]) - np.maximum(y1[i], y1[order[1:]]) + 1)
        inter = w * h
        ovr = inter / (areas[i] + areas[order[1:]] - inter)
        order = order[np.where(ovr <= thr)[0] + 1]
    return keep


def yolox_reference(model: Path, image: np.ndarray, decoded_in_graph: bool) -> list[Det]:
    session = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    x, ratio = yolox_preproc(image, INPUT_HW)
    output = session.run(None, {session.get_inputs()[0].name: x[None]})[0]
    predictions = output[0] if decoded_in_graph else demo_postprocess(output, INPUT_HW)[0]
    boxes = predictions[:, :4]
    scores = predictions[:, 4:5] * predictions[:, 5:]
    xyxy = np.ones_like(boxes)
    xyxy[:, 0] = boxes[:, 0] - boxes[:, 2] / 2.0
    xyxy[:, 1] = boxes[:, 1] - boxes[:, 3] / 2.0
    xyxy[:, 2] = boxes[:, 0] + boxes[:, 2] / 2.0
    xyxy[:, 3] = boxes[:, 1] + boxes[:, 3] / 2.0
    xyxy /= ratio
    # multiclass_nms(..., class_agnostic=True)
    cls = scores.argmax(1)
    best = scores[np.arange(len(cls)), cls]
    valid = best > SCORE_THR
    keep = nms_plus_one(xyxy[valid], best[valid], NMS_THR)
    kept, kept_scores, kept_cls = xyxy[valid][keep], best[valid][keep], cls[valid][keep]
    h0, w0 = image.shape[:2]
    kept[:, 0::2] = kept[:, 0::2].clip(0, w0)
    kept[:, 1::2] = kept[:, 1::2].clip(0, h0)
    return [
        (f"class{int(c)}", float(s), (b[0], b[1], b[2], b[3]))
        for b, s, c in zip(kept.tolist(), kept_scores, kept_cls, strict=True)
    ]


@pytest.fixture(params=[False, True], ids=["raw", "decoded"])
def tiny_yolox(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[Path, bool]:
    """YOLOX as export_onnx.py writes it: raw head outputs, or with --decode_in_inference."""
    decoded = bool(request.param)
    return yolox_model(tmp_path / "yolox.onnx", INPUT_HW, NC, decoded=decoded), decoded


def _image(realdata: Path, name: str) -> np.ndarray:
    return cv2.imread(str(kit_path(realdata, KIT, "images", name)), cv2.IMREAD_COLOR)


@pytest.mark.parametrize("name", IMAGES)
def test_yolox_detections_equal_yolox_processing(
    realdata: Path, tiny_yolox: tuple[Path, bool], name: str
) -> None:
    model, decoded = tiny_yolox
    image = _image(realdata, name)
    want = yolox_reference(model, image, decoded)
    assert len(want) >= 5, "the tiny model must detect something for the test to mean anything"
    got = trapflow_detections(model, image, **PARAMS)
    assert_same(got, want, f"{name}, YOLOX {'decoded' if decoded else 'raw'} export")
    # Boxes of different classes overlap here: per-class NMS would keep other boxes.
    assert differ(trapflow_detections(model, image, agnostic_nms=False, **PARAMS), want)


@pytest.mark.parametrize("name", IMAGES)
def test_yolox_input_tensor_is_yolox_preproc(
    realdata: Path, tiny_yolox: tuple[Path, bool], name: str
) -> None:
    """Bit for bit: the tensor trapflow feeds a YOLOX model is the one YOLOX's preproc makes."""
    model, decoded = tiny_yolox
    det = CrabDetector()
    det.configure({"model": str(model)}, make_context(pool="mono"))
    assert det.layout == ("yolox_decoded" if decoded else "yolox")
    image = _image(realdata, name)
    tensor, lb = det.preprocess(image)
    want, ratio = yolox_preproc(image, INPUT_HW)
    assert lb.scale == ratio
    assert np.array_equal(tensor[0], want)


@pytest.mark.parametrize("name", IMAGES)
def test_centred_letterbox_on_yolox_gives_other_detections(
    realdata: Path, tiny_yolox: tuple[Path, bool], name: str
) -> None:
    """Regression: YOLOX models were letterboxed the Ultralytics way (centred), as issue 12
    found on a real COCO photo (a box moved 20 px, a false box appeared). Centred, the
    image lands on other grid cells and the detections leave YOLOX's; top-left, they match."""
    model, decoded = tiny_yolox
    image = _image(realdata, name)
    want = yolox_reference(model, image, decoded)
    centred = trapflow_detections(model, image, letterbox="center", **PARAMS)
    assert differ(centred, want)
    topleft = trapflow_detections(model, image, letterbox="topleft", **PARAMS)
    assert_same(topleft, want, f"{name}, letterbox topleft")
