"""Letterbox and input tensor, layout detection, decoders and NMS for YOLO-family detectors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from trapflow_workers.yolo_decode import (
    DEFAULT_STRIDES,
    _yolox_grid,
    check_layout,
    decode,
    detect_layout,
    grid_size,
    nms,
)
from trapflow_workers.yolo_preprocess import (
    Placement,
    Preprocessor,
    allocate_tensor,
    fit,
    letterbox,
)

from tests.kits.onnx_models import yolo_tensor
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


@pytest.mark.parametrize(
    ("shape", "size", "placement", "expected"),
    [
        # (height, width) -> (scale, pad_x, pad_y, width, height)
        ((720, 1280), (640, 640), "center", (0.5, 0, 140, 640, 360)),
        ((720, 1280), (640, 640), "topleft", (0.5, 0, 0, 640, 360)),
        ((1080, 810), (640, 640), "center", (640 / 1080, 80, 0, 480, 640)),
        # 640 * 0.65 = 277.55 (427 rows): YOLOX truncates, Ultralytics rounds and
        # puts the odd padding pixel at the bottom.
        ((427, 640), (416, 416), "topleft", (0.65, 0, 0, 416, 277)),
        ((427, 640), (416, 416), "center", (0.65, 0, 69, 416, 278)),
    ],
)
def test_fit_places_the_image_as_each_toolchain(
    shape: tuple[int, int], size: tuple[int, int], placement: Placement, expected: tuple
) -> None:
    lb = fit(shape[0], shape[1], size, placement)
    assert (lb.scale, lb.pad_x, lb.pad_y, lb.width, lb.height) == pytest.approx(expected)


def _reference_tensor(
    img: np.ndarray,
    size: tuple[int, int],
    placement: Placement,
    rgb: bool,
    scale: float,
    mean: tuple[float, float, float],
    std: tuple[float, float, float],
) -> np.ndarray:
    """Written here from the toolchains' steps, independently of yolo_preprocess."""
    boxed, _ = letterbox(img, size, 114, placement)
    x = boxed[:, :, ::-1] if rgb else boxed
    x = x.transpose(2, 0, 1).astype(np.float32)
    x = x / np.float32(255.0) if scale == 1 / 255 else x * np.float32(scale)
    x = (x - np.float32(mean).reshape(3, 1, 1)) / np.float32(std).reshape(3, 1, 1)
    return x[None]


@pytest.mark.parametrize(
    ("placement", "rgb", "scale", "mean", "std", "nhwc", "dtype"),
    [
        ("center", True, 1 / 255, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), False, np.float32),
        ("topleft", False, 1.0, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), False, np.float32),
        ("center", True, 0.5, (0.4, 0.5, 0.6), (0.2, 0.25, 0.3), True, np.float32),
        ("topleft", True, 1 / 255, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), False, np.float16),
    ],
)
def test_preprocessor_equals_letterbox_then_conversion(
    placement: Placement,
    rgb: bool,
    scale: float,
    mean: tuple[float, float, float],
    std: tuple[float, float, float],
    nhwc: bool,
    dtype: type[np.floating],
) -> None:
    rng = np.random.default_rng(3)
    pre = Preprocessor((320, 320), placement, 114, rgb, scale, mean, std, nhwc, dtype)
    # Frames of changing sizes: the padding is rebuilt, the buffer reused.
    for shape in [(480, 640), (300, 200), (480, 640), (320, 320)]:
        img = rng.integers(0, 256, (*shape, 3), np.uint8)
        tensor, lb = pre(img)
        ref = _reference_tensor(img, (320, 320), placement, rgb, scale, mean, std)
        got = tensor.transpose(0, 3, 1, 2) if nhwc else tensor
        assert got.dtype == dtype
        if dtype == np.float32:  # the same float32 operations in the same order
            assert np.array_equal(got, ref)
        else:  # float16: 11 significant bits
            np.testing.assert_allclose(got, ref, rtol=1e-3, atol=1e-3)
        assert lb == fit(shape[0], shape[1], (320, 320), placement)
    assert pre(img)[0] is tensor  # one buffer, no allocation per frame


# YOLOX's preproc (top-left, BGR, pixels 0..255) and Ultralytics' LetterBox (centred, RGB, /255)
TOOLCHAINS = [("topleft", False, 1.0), ("center", True, 1 / 255)]


@pytest.mark.parametrize(("placement", "rgb", "scale"), TOOLCHAINS, ids=["yolox", "ultralytics"])
@pytest.mark.parametrize("nhwc", [False, True], ids=["nchw", "nhwc"])
@pytest.mark.parametrize("input_hw", [(320, 320), (640, 640), (384, 640)])
def test_preallocated_tensor_is_bit_identical_to_the_allocating_path(
    placement: Placement, rgb: bool, scale: float, nhwc: bool, input_hw: tuple[int, int]
) -> None:
    """Preprocessor writes the letterbox into one preallocated input (cv2.resize into a
    kept buffer, the conversion with out=): the same bits as allocate_tensor, which makes a
    new array at every step, on frames smaller, larger, taller and wider than the input,
    one size after another through the same buffer (the padding is rebuilt on a change)."""
    rng = np.random.default_rng(11)
    pre = Preprocessor(input_hw, placement, 114, rgb, scale, nhwc=nhwc)
    first = None
    for shape in [(720, 1280), (1080, 1920), (480, 640), (1280, 720), (321, 479), (720, 1280),
                  (200, 150), input_hw]:
        img = cv2.GaussianBlur(rng.integers(0, 256, (*shape, 3), np.uint8), (5, 5), 2)
        tensor, lb = pre(img)
        want, want_lb = allocate_tensor(img, input_hw, placement, 114, rgb, scale, nhwc=nhwc)
        assert tensor.shape == want.shape and tensor.dtype == want.dtype == np.float32
        assert np.array_equal(tensor, want), f"{shape} into {input_hw}"
        assert lb == want_lb
        first = tensor if first is None else first
        assert tensor is first  # the one buffer, written in place every time
    # And the reference itself agrees with the steps written out in this test.
    if not nhwc:
        assert np.array_equal(want, _reference_tensor(img, input_hw, placement, rgb, scale,
                                                      (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)))


def test_preprocessor_divides_by_255_bit_for_bit() -> None:
    """Ultralytics divides by 255; multiplying by 1/255 differs in the last bit."""
    img = np.arange(256, dtype=np.uint8).repeat(3).reshape(16, 16, 3)
    tensor, _ = Preprocessor((16, 16), "center", 114, True, 1 / 255)(img)
    expected = img[:, :, ::-1].transpose(2, 0, 1).astype(np.float32) / np.float32(255.0)
    assert np.array_equal(tensor[0], expected)


def test_yolox_raw_and_decoded_outputs_are_told_apart() -> None:
    hw = (320, 320)
    raw = yolo_tensor("yolox", BOXES, [0, 2], [0.9, 0.8], nc=3, input_hw=hw)
    grid, stride = _yolox_grid(hw, DEFAULT_STRIDES)
    decoded = raw.copy()
    decoded[0, :, :2] = (raw[0, :, :2] + grid) * stride
    decoded[0, :, 2:4] = np.exp(raw[0, :, 2:4]) * stride
    assert detect_layout(raw.shape, hw, 3, sample=raw) == "yolox"
    assert detect_layout(decoded.shape, hw, 3, sample=decoded) == "yolox_decoded"
    for layout, out in (("yolox", raw), ("yolox_decoded", decoded)):
        boxes, scores, ids = decode(out, layout, 0.25, hw)  # type: ignore[arg-type]
        order = np.argsort(-scores)
        np.testing.assert_allclose(boxes[order], BOXES, atol=1e-3)
        assert ids[order].tolist() == [0, 2]


def test_nms_class_agnostic_and_whole_pixel_edges() -> None:
    boxes = np.array([[0, 0, 10, 10], [0, 0, 10, 10], [0, 0, 9, 12]], float)
    scores = np.array([0.9, 0.8, 0.7])
    ids = np.array([0, 1, 0])
    assert nms(boxes, scores, ids, iou=0.5).tolist() == [0, 1]
    assert nms(boxes, scores, ids, iou=0.5, agnostic=True).tolist() == [0]
    # IoU of the first and last box: 90/120 = 0.75 as areas, 110/(121+130-110) = 0.780
    # with YOLOX's +1 pixel edges; a threshold between the two tells them apart.
    assert nms(boxes, scores, ids, iou=0.77, agnostic=True).tolist() == [0, 2]
    assert nms(boxes, scores, ids, iou=0.77, agnostic=True, pixel=1.0).tolist() == [0]
