"""The mono_ir detector plugin with real ONNX models run by onnxruntime."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from trapflow_workers.crab_detector import CrabDetector
from trapflow_workers.onnx_session import open_session

from tests.kits.onnx_models import constant_detector, yolo_tensor
from trapflow.errors import WorkerError
from trapflow.testing.kit import make_context, make_pair
from trapflow.wire.messages import MonoIR

HW = (320, 320)
# Boxes in model input pixels; a 640x480 frame is scaled by 0.5 and padded 40 px top
# (Ultralytics' centred letterbox) or placed at the top-left (YOLOX's preproc).
INPUT_BOXES = [(40.0, 60.0, 120.0, 140.0), (200.0, 100.0, 260.0, 160.0)]
IMAGE_BOXES = [(80.0, 40.0, 240.0, 200.0), (400.0, 120.0, 520.0, 240.0)]
IMAGE_BOXES_TOPLEFT = [(80.0, 120.0, 240.0, 280.0), (400.0, 200.0, 520.0, 320.0)]


def _model(tmp_path: Path, layout: str, n: int = 500, **kw: Any) -> Path:
    out = yolo_tensor(layout, INPUT_BOXES, [0, 1], [0.9, 0.6], nc=2, input_hw=HW, n=n)  # type: ignore[arg-type]
    return constant_detector(tmp_path / f"{layout}.onnx", out, HW, **kw)


def _run(params: dict[str, Any]) -> list[Any]:
    det = CrabDetector()
    det.configure(params, make_context(pool="mono"))
    frame = np.zeros((480, 640, 3), np.uint8)
    return det.process(make_pair(frame)).detections


@pytest.mark.parametrize("layout", ["yolov8", "yolov5", "yolox"])
def test_detects_known_boxes_in_image_pixels(tmp_path: Path, layout: str) -> None:
    labels = tmp_path / "labels.txt"
    labels.write_text("crab\nfish\n")
    dets = _run({"model": str(_model(tmp_path, layout)), "labels": str(labels)})
    assert [d.label for d in dets] == ["crab", "fish"]
    assert [d.confidence for d in dets] == pytest.approx([0.9, 0.6])
    expected = IMAGE_BOXES_TOPLEFT if layout == "yolox" else IMAGE_BOXES
    np.testing.assert_allclose([d.box for d in dets], expected, atol=0.01)


@pytest.mark.parametrize(
    ("layout", "placement", "rgb", "scale", "agnostic"),
    [
        ("yolov8", "center", True, 1 / 255, False),
        ("yolov5", "center", True, 1 / 255, False),
        ("yolox", "topleft", False, 1.0, True),
    ],
)
def test_each_layout_gets_its_toolchains_processing(
    tmp_path: Path, layout: str, placement: str, rgb: bool, scale: float, agnostic: bool
) -> None:
    det = CrabDetector()
    det.configure({"model": str(_model(tmp_path, layout))}, make_context(pool="mono"))
    pre = det.preprocess
    assert (pre.placement, pre.fill, pre.rgb, pre.scale) == (placement, 114, rgb, scale)
    assert det.agnostic is agnostic


def test_preprocessing_from_params_then_metadata(tmp_path: Path) -> None:
    """Params win over metadata, metadata over the layout's toolchain defaults."""
    meta = {"letterbox": "topleft", "pad_value": "0", "color_order": "bgr", "scale": "1"}
    dets = _run({"model": str(_model(tmp_path, "yolov8", metadata=meta))})
    np.testing.assert_allclose([d.box for d in dets], IMAGE_BOXES_TOPLEFT, atol=0.01)
    det = CrabDetector()
    det.configure({"model": str(_model(tmp_path, "yolov8", metadata=meta))}, make_context())
    assert (det.preprocess.fill, det.preprocess.rgb, det.preprocess.scale) == (0, False, 1.0)
    dets = _run(
        {"model": str(_model(tmp_path, "yolox")), "letterbox": "center", "agnostic_nms": False}
    )
    np.testing.assert_allclose([d.box for d in dets], IMAGE_BOXES, atol=0.01)
    frame = np.full((480, 640, 3), 200, np.uint8)
    det.configure(
        {"model": str(_model(tmp_path, "yolov8")), "pad_value": 0, "color": "bgr"},
        make_context(pool="mono"),
    )
    tensor, lb = det.preprocess(frame)
    assert (lb.pad_x, lb.pad_y) == (0, 40)
    assert tensor[0, :, 0, 0].tolist() == [0.0, 0.0, 0.0]  # the padding
    assert tensor[0, :, 100, 100].tolist() == pytest.approx([200 / 255] * 3)


def test_labels_from_ultralytics_metadata_and_layout_override(tmp_path: Path) -> None:
    # 6 rows: with 2 classes [1, 6, 6] is ambiguous by shape alone, names settle it.
    meta = {"names": "{0: 'crab', 1: 'scallop'}", "imgsz": "[320, 320]"}
    path = _model(tmp_path, "yolov8", n=6, metadata=meta, dynamic=True)
    dets = _run({"model": str(path), "confidence": 0.7})
    assert [d.label for d in dets] == ["crab"]
    np.testing.assert_allclose(dets[0].box, IMAGE_BOXES[0], atol=0.01)


def test_dynamic_input_size_from_params(tmp_path: Path) -> None:
    path = _model(tmp_path, "yolov5", dynamic=True)
    dets = _run({"model": str(path), "input_size": [320, 320], "layout": "yolov5"})
    np.testing.assert_allclose([d.box for d in dets], IMAGE_BOXES, atol=0.01)
    assert [d.label for d in dets] == ["class0", "class1"]


def test_provider_fallback_logs_the_provider_used(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = _model(tmp_path, "yolov8")
    with caplog.at_level(logging.INFO, logger="trapflow_workers.onnx_session"):
        session = open_session(path, ["tensorrt", "cuda", "cpu"], threads=1)
    assert session.provider in session.session.get_providers()
    line = next(r.getMessage() for r in caplog.records if "runs on" in r.getMessage())
    assert session.provider in line
    if session.provider == "CPUExecutionProvider":
        assert "TensorrtExecutionProvider" in line


@pytest.mark.parametrize(
    ("params", "setup", "error"),
    [
        ({"model": "{tmp}/missing.onnx"}, None, "model file not found"),
        ({"model": "{tmp}/bad.onnx"}, "garbage", "cannot load ONNX model"),
        ({"model": "{tmp}/yolov8.onnx", "threads": 0}, "yolov8", r"pools\.mono\.params\.threads"),
        ({"model": "{tmp}/yolov8.onnx", "colour": "rgb"}, "yolov8", r"pools\.mono\.params\.colour"),
        (
            {"model": "{tmp}/yolov8.onnx", "providers": ["warp"]},
            "yolov8",
            "unknown execution provider",
        ),
        ({"model": "{tmp}/yolov8.onnx", "layout": "yolox"}, "yolov8", "does not fit layout yolox"),
        ({"model": "{tmp}/yolov8.onnx", "labels": "{tmp}/three.txt"}, "yolov8", "for 3 classes"),
        (
            {"model": "{tmp}/yolov8.onnx", "input_size": [640, 640]},
            "yolov8",
            "fixed input of 320x320",
        ),
        ({"model": "{tmp}/odd.onnx"}, "odd", "matches no decoder"),
        ({"model": "{tmp}/yolov8.onnx", "letterbox": "middle"}, "yolov8", r"params\.letterbox"),
        ({"model": "{tmp}/yolov8.onnx", "pad_value": 256}, "yolov8", r"params\.pad_value"),
        (
            {"model": "{tmp}/yolov8.onnx"},
            "meta:letterbox=middle",
            "metadata 'letterbox': expected one of center, topleft, got 'middle'",
        ),
        (
            {"model": "{tmp}/yolov8.onnx"},
            "meta:pad_value=300",
            "metadata 'pad_value': expected an integer 0..255, got '300'",
        ),
        (
            {"model": "{tmp}/yolov8.onnx"},
            "meta:scale=1/255",
            r"metadata 'scale': expected a number, got '1/255' .*params\.scale",
        ),
        (
            {"model": "{tmp}/yolov8.onnx"},
            "meta:color_order=bgra",
            r"metadata 'color_order': expected one of rgb, bgr, got 'bgra' .*params\.color\)",
        ),
        (
            {"model": "{tmp}/yolov8.onnx"},
            "meta:layout=yolov9",
            "metadata 'layout': expected one of yolov8, yolov5, yolox, yolox_decoded",
        ),
    ],
)
def test_configure_rejects(
    tmp_path: Path, params: dict[str, Any], setup: str | None, error: str
) -> None:
    if setup == "garbage":
        (tmp_path / "bad.onnx").write_bytes(b"not a model")
    elif setup == "odd":
        constant_detector(tmp_path / "odd.onnx", np.zeros((1, 4, 3), np.float32), HW)
    elif setup and setup.startswith("meta:"):
        key, value = setup[5:].split("=", 1)
        _model(tmp_path, "yolov8", metadata={key: value})
    elif setup:
        _model(tmp_path, setup)
    (tmp_path / "three.txt").write_text("a\nb\nc\n")
    params = {k: v.format(tmp=tmp_path) if isinstance(v, str) else v for k, v in params.items()}
    with pytest.raises(WorkerError, match=error):
        CrabDetector().configure(params, make_context(pool="mono"))


def test_wrong_frame_size_is_a_worker_error(tmp_path: Path) -> None:
    det = CrabDetector()
    det.configure({"model": str(_model(tmp_path, "yolov8"))}, make_context(pool="mono"))
    frame = np.zeros((480, 640, 3), np.uint8)
    with pytest.raises(WorkerError, match="header says 1280x720"):
        det.process(make_pair(frame, header_size=(1280, 720)))
    with pytest.raises(WorkerError, match="BGR uint8"):
        det.process(make_pair(frame[:, :, 0]))


@pytest.mark.parametrize(("layout", "size", "reduction"), [
    ("yolov8", (1280, 720), 4), ("yolox", (1280, 720), 4), ("yolov8", (1920, 1080), 4),
    ("yolov8", (640, 480), 2), ("yolox", (600, 400), 1),
])
def test_jpeg_decoded_at_reduced_scale_gives_boxes_in_frame_pixels(
    tmp_path: Path, layout: str, size: tuple[int, int], reduction: int
) -> None:
    """The detector covers its letterbox of the run's frames (max_size); a JPEG pair is then
    decoded at 1/2, 1/4 or 1/8 and its boxes mapped back by the reduction. With a model whose
    output ignores the pixels the boxes equal those of the full frame exactly."""
    from tests import builders
    from trapflow.calibration.camera import StereoRig
    from trapflow.pools.pair_path import decode_pair, to_frame_pixels

    w, h = size
    det = CrabDetector()
    det.configure({"model": str(_model(tmp_path, layout))},
                  make_context(StereoRig.from_fov(w, h, 70.0, 0.12), pool="mono"))
    r = min(HW[0] / h, HW[1] / w)
    assert det.max_size == pytest.approx((w * r, h * r), abs=1)
    img = builders.image(w, h, seed=5)
    data = builders.jpeg(img)
    pair = decode_pair(det, builders.pair_header(3, w, h, "jpeg"), data, data)
    assert pair.reduction == reduction
    assert pair.left.shape == (h // reduction, w // reduction, 3)
    body = det.process(pair)  # in the reduced image's pixels; the runtime maps them back
    assert isinstance(body, MonoIR)
    got = [d.box for d in to_frame_pixels(body, pair.reduction, w, h).detections]
    want = [d.box for d in det.process(make_pair(img)).detections]
    assert len(got) == 2
    np.testing.assert_allclose(got, want, atol=1e-3)
    raw = decode_pair(det, builders.pair_header(3, w, h, "raw"), img.tobytes(), img.tobytes())
    assert raw.reduction == 1 and raw.left.shape == img.shape  # raw frames stay whole


def test_variant_int8_runs_the_packaged_int8_model() -> None:
    """`variant: int8` picks the quantized demo model; its metadata gives labels and layout
    as the fp32 one does (accuracy is checked on held-out scenes in test_synth_models)."""
    onnx = pytest.importorskip("onnx")
    det = CrabDetector()
    det.configure({"variant": "int8", "providers": ["cpu"]}, make_context(pool="mono"))
    assert det.session.path.name == "crab_detector_int8.onnx"
    assert det.labels == ["crab", "scallop"] and det.layout == "yolov8"
    ops = {n.op_type for n in onnx.load(str(det.session.path)).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= ops  # QDQ: int8 inside


@pytest.mark.parametrize(("params", "model"), [
    ({}, "crab_detector_int8.onnx"),  # no variant: int8, the default since issue 27
    ({"variant": ""}, "crab_detector_int8.onnx"),  # empty says the same
    ({"variant": "fp32"}, "crab_detector.onnx"),  # fp32 stays one key away
])
def test_the_packaged_default_is_int8(params: dict[str, str], model: str) -> None:
    det = CrabDetector()
    det.configure({**params, "providers": ["cpu"]}, make_context(pool="mono"))
    assert det.session.path.name == model


def test_variant_fp32_beside_a_model_path_runs_that_model(tmp_path: Path) -> None:
    """A config that named its model and `variant: fp32` (accepted before int8 became the
    default) still runs its own model."""
    path = _model(tmp_path, "yolov8")
    det = CrabDetector()
    det.configure({"model": str(path), "variant": "fp32"}, make_context(pool="mono"))
    assert det.session.path == path


def test_variant_with_a_model_path_is_refused(tmp_path: Path) -> None:
    det = CrabDetector()
    with pytest.raises(WorkerError, match=r"params\.variant: 'int8' picks a packaged"):
        det.configure({"model": str(_model(tmp_path, "yolov8")), "variant": "int8"},
                      make_context(pool="mono"))
