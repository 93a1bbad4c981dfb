"""Tiny real ONNX models with known answers, for tests and benches (needs the `onnx` package).

Detectors emit a YOLOv8, YOLOv5 or YOLOX shaped tensor that encodes given boxes
(plus zero times the input, so the graph really consumes the image); the classifier
maps the mean colour of the stereo pair to logits.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper
from trapflow_workers.yolo_decode import DEFAULT_STRIDES, Layout

OPSET = 17
IR_VERSION = 8


def _save(graph: onnx.GraphProto, path: Path, metadata: Mapping[str, str] | None) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = IR_VERSION
    for key, value in (metadata or {}).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path


def yolo_tensor(
    layout: Layout,
    boxes: Sequence[tuple[float, float, float, float]],
    classes: Sequence[int],
    scores: Sequence[float],
    nc: int,
    input_hw: tuple[int, int],
    n: int = 0,
    strides: tuple[int, ...] = DEFAULT_STRIDES,
) -> np.ndarray:
    """The raw output a YOLO head would give for these xyxy boxes (model input pixels)."""
    h, w = input_hw
    if layout == "yolox":
        n = sum((h // s) * (w // s) for s in strides)
    n = max(n, len(boxes))
    rows = np.zeros((n, 5 + nc), np.float32)
    if layout == "yolox":
        # Put each box into the stride-8 cell that contains its centre.
        s, gw = strides[0], w // strides[0]
        for box, cls, score in zip(boxes, classes, scores, strict=True):
            cx, cy, bw, bh = (
                (box[0] + box[2]) / 2,
                (box[1] + box[3]) / 2,
                box[2] - box[0],
                box[3] - box[1],
            )
            gx, gy = int(cx // s), int(cy // s)
            rows[gy * gw + gx, :4] = (cx / s - gx, cy / s - gy, np.log(bw / s), np.log(bh / s))
            rows[gy * gw + gx, 4] = 1.0
            rows[gy * gw + gx, 5 + cls] = score
        return rows[None]
    for i, (box, cls, score) in enumerate(zip(boxes, classes, scores, strict=True)):
        rows[i, :4] = (
            (box[0] + box[2]) / 2,
            (box[1] + box[3]) / 2,
            box[2] - box[0],
            box[3] - box[1],
        )
        rows[i, 4] = 1.0
        rows[i, 5 + cls] = score
    if layout == "yolov5":
        return rows[None]
    v8 = np.concatenate([rows[:, :4], rows[:, 5:]], axis=1)  # no objectness column
    return np.ascontiguousarray(v8.T[None])


def constant_detector(
    path: Path,
    output: np.ndarray,
    input_hw: tuple[int, int] = (320, 320),
    dynamic: bool = False,
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """A detector whose output is `output` + 0 * mean(image)."""
    h, w = input_hw
    dims: list[int | str] = [1, 3, "height", "width"] if dynamic else [1, 3, h, w]
    image = helper.make_tensor_value_info("images", TensorProto.FLOAT, dims)
    out = helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(output.shape))
    nodes = [
        helper.make_node("ReduceMean", ["images"], ["m"], keepdims=0),
        helper.make_node("Mul", ["m", "zero"], ["z"]),
        helper.make_node("Add", ["table", "z"], ["output0"]),
    ]
    inits = [
        numpy_helper.from_array(output.astype(np.float32), "table"),
        numpy_helper.from_array(np.zeros((), np.float32), "zero"),
    ]
    return _save(helper.make_graph(nodes, "detector", [image], [out], inits), path, metadata)


def colour_classifier(
    path: Path,
    input_hw: tuple[int, int] = (64, 128),
    arrangement: str = "concat_channels",
    metadata: Mapping[str, str] | None = None,
    gain: float = 10.0,
) -> Path:
    """Logits of classes (blue, green, red): the mean of each BGR channel over both images.

    The model takes RGB input scaled to 0..1; arrangement is concat_channels
    ([1, 6, H, W]), side_by_side ([1, 3, H, 2W]) or two_inputs (two [1, 3, H, W]).
    """
    h, w = input_hw
    # RGB input -> logits for (blue, green, red): pick channel 2, 1, 0.
    pick = np.zeros((3, 3), np.float32)
    pick[0, 2] = pick[1, 1] = pick[2, 0] = gain
    nodes: list[onnx.NodeProto] = []
    inits = []
    if arrangement == "two_inputs":
        inputs = [
            helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, 3, h, w])
            for n in ("left", "right")
        ]
        nodes += [
            helper.make_node("Add", ["left", "right"], ["sum"]),
            helper.make_node("GlobalAveragePool", ["sum"], ["gap"]),
        ]
        weights = pick * 0.5
    elif arrangement == "concat_channels":
        inputs = [helper.make_tensor_value_info("pair", TensorProto.FLOAT, [1, 6, h, w])]
        nodes.append(helper.make_node("GlobalAveragePool", ["pair"], ["gap"]))
        weights = np.concatenate([pick, pick], axis=1) * 0.5
    elif arrangement == "side_by_side":
        inputs = [helper.make_tensor_value_info("pair", TensorProto.FLOAT, [1, 3, h, 2 * w])]
        nodes.append(helper.make_node("GlobalAveragePool", ["pair"], ["gap"]))
        weights = pick
    else:
        raise ValueError(f"unknown arrangement {arrangement!r}")
    inits += [
        numpy_helper.from_array(weights.astype(np.float32), "W"),
        numpy_helper.from_array(np.zeros(3, np.float32), "B"),
    ]
    nodes += [
        helper.make_node("Flatten", ["gap"], ["flat"]),
        helper.make_node("Gemm", ["flat", "W", "B"], ["logits"], transB=1),
    ]
    out = helper.make_tensor_value_info("logits", TensorProto.FLOAT, [1, 3])
    return _save(helper.make_graph(nodes, "classifier", inputs, [out], inits), path, metadata)
