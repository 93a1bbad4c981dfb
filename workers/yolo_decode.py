"""Pure-numpy post-processing for YOLO-family detectors: layout detection, decoders, NMS.

Layouts (batch 1):
  yolov8         [1, 4+nc, N]  Ultralytics YOLOv8 / YOLO11: cx, cy, w, h, class scores
  yolov5         [1, N, 5+nc]  YOLOv5: cx, cy, w, h, objectness, class scores
  yolox          [1, N, 5+nc]  YOLOX as its export_onnx.py writes it by default (no
                               --decode_in_inference): grid offsets and log sizes per
                               stride, objectness and class scores (sigmoided)
  yolox_decoded  [1, N, 5+nc]  YOLOX exported with --decode_in_inference: cx, cy, w, h in
                               input pixels, objectness, class scores
Scores are objectness x class score where there is an objectness column.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from trapflow.plugin import WorkerError

Layout = Literal["yolov8", "yolov5", "yolox", "yolox_decoded"]
LAYOUTS: tuple[Layout, ...] = ("yolov8", "yolov5", "yolox", "yolox_decoded")
DEFAULT_STRIDES = (8, 16, 32)
MAX_CANDIDATES = 4096  # boxes kept for NMS, best first; bounds its quadratic cost


def grid_size(input_hw: tuple[int, int], strides: tuple[int, ...] = DEFAULT_STRIDES) -> int:
    """Anchor points of an anchor-free head over all strides (YOLOX, YOLOv8)."""
    h, w = input_hw
    return sum((h // s) * (w // s) for s in strides)


def detect_layout(
    shape: tuple[int, ...],
    input_hw: tuple[int, int],
    nc: int | None,
    strides: tuple[int, ...] = DEFAULT_STRIDES,
    sample: np.ndarray | None = None,
) -> Layout:
    """Choose the decoder from the output shape; WorkerError when no decoder fits.

    With known class count nc the channel axis is unambiguous; without it the
    shorter axis is taken as channels. [1, N, 5+nc] is YOLOX when N equals the
    anchor-free grid size of the input, YOLOv5 (3 anchors per cell) otherwise.
    A YOLOX output is raw grid offsets (`yolox`) unless `sample`, one output of
    the model, shows boxes already decoded (`yolox_decoded`, see yolox_is_decoded).
    """
    layout = _layout_of_shape(shape, input_hw, nc, strides)
    if layout == "yolox" and sample is not None and yolox_is_decoded(sample, input_hw, strides):
        return "yolox_decoded"
    return layout


def yolox_is_decoded(
    output: np.ndarray, input_hw: tuple[int, int], strides: tuple[int, ...] = DEFAULT_STRIDES
) -> bool:
    """Whether a [1, N, 5+nc] YOLOX output holds box centres in input pixels.

    Decoded centres sit near their grid cell's centre (xy ~ (cell + 0.5) * stride,
    hundreds of pixels across the input); raw ones are offsets near 0..1 in every
    cell. Whichever the centres lie closer to, over all cells, decides.
    """
    xy = np.asarray(output, dtype=np.float64)[0, :, :2]
    grid, stride = _yolox_grid(input_hw, strides)
    as_decoded = np.median(np.abs(xy - (grid + 0.5) * stride) / stride)
    as_raw = np.median(np.abs(xy - 0.5))
    return bool(as_decoded < as_raw)


def _layout_of_shape(
    shape: tuple[int, ...],
    input_hw: tuple[int, int],
    nc: int | None,
    strides: tuple[int, ...],
) -> Layout:
    if len(shape) != 3 or shape[0] != 1:
        raise WorkerError(
            f"detector output: expected [1, 4+nc, N] or [1, N, 5+nc], got {list(shape)}"
        )
    _, a, b = shape
    if nc is not None:
        if a == 4 + nc and b != 5 + nc:
            return "yolov8"
        if b == 5 + nc and a != 4 + nc:
            return "yolox" if a == grid_size(input_hw, strides) else "yolov5"
        if a == 4 + nc and b == 5 + nc:
            return "yolov8"
        raise WorkerError(
            f"detector output {list(shape)} matches no decoder for {nc} classes: expected "
            f"[1, {4 + nc}, N] (yolov8) or [1, N, {5 + nc}] (yolov5/yolox)"
        )
    if a < b and a >= 5:
        return "yolov8"
    if b < a and b >= 6:
        return "yolox" if a == grid_size(input_hw, strides) else "yolov5"
    raise WorkerError(
        f"detector output {list(shape)} matches no decoder: expected "
        "[1, 4+nc, N] (yolov8) or [1, N, 5+nc] (yolov5/yolox)"
    )


def check_layout(
    layout: Layout,
    shape: tuple[int, ...],
    input_hw: tuple[int, int],
    strides: tuple[int, ...] = DEFAULT_STRIDES,
) -> int:
    """Check that a (forced) layout fits the output shape; returns the class count."""
    if len(shape) != 3 or shape[0] != 1:
        raise WorkerError(f"detector output: expected rank 3 with batch 1, got {list(shape)}")
    if layout not in LAYOUTS:
        raise WorkerError(f"detector layout: expected one of {', '.join(LAYOUTS)}, got {layout!r}")
    nc = shape[1] - 4 if layout == "yolov8" else shape[2] - 5
    if nc < 1:
        raise WorkerError(
            f"detector output {list(shape)} does not fit layout {layout}: no class columns left"
        )
    if layout == "yolox" and shape[1] != grid_size(input_hw, strides):
        raise WorkerError(
            f"detector output {list(shape)} does not fit layout yolox: expected "
            f"N={grid_size(input_hw, strides)} grid cells for input {input_hw}, strides {strides}"
        )
    return nc


def _xywh_to_xyxy(b: np.ndarray) -> np.ndarray:
    half = b[:, 2:4] / 2.0
    return np.concatenate([b[:, 0:2] - half, b[:, 0:2] + half], axis=1)


def _yolox_grid(
    input_hw: tuple[int, int], strides: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray]:
    grids, expanded = [], []
    h, w = input_hw
    for s in strides:
        gy, gx = np.meshgrid(np.arange(h // s), np.arange(w // s), indexing="ij")
        grids.append(np.stack([gx, gy], axis=-1).reshape(-1, 2))
        expanded.append(np.full(((h // s) * (w // s), 1), s))
    return np.concatenate(grids).astype(np.float32), np.concatenate(expanded).astype(np.float32)


def decode(
    output: np.ndarray,
    layout: Layout,
    conf: float,
    input_hw: tuple[int, int],
    strides: tuple[int, ...] = DEFAULT_STRIDES,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate boxes (xyxy, model input pixels), scores and class ids with score > conf."""
    out = np.asarray(output, dtype=np.float32)[0]
    if layout == "yolov8":
        rows = out.T
        boxes, cls_scores = rows[:, :4], rows[:, 4:]
        class_ids = cls_scores.argmax(axis=1)
        scores = cls_scores[np.arange(len(rows)), class_ids]
    else:
        rows = out
        boxes = rows[:, :4]
        if layout == "yolox":
            grid, stride = _yolox_grid(input_hw, strides)
            boxes = np.concatenate(
                [(boxes[:, :2] + grid) * stride, np.exp(np.minimum(boxes[:, 2:4], 20.0)) * stride],
                axis=1,
            )
        class_ids = rows[:, 5:].argmax(axis=1)
        scores = rows[:, 4] * rows[np.arange(len(rows)), 5 + class_ids]
    keep = scores > conf  # strictly above, as Ultralytics, YOLOv5 and YOLOX all filter
    boxes, scores, class_ids = boxes[keep], scores[keep], class_ids[keep]
    if len(scores) > MAX_CANDIDATES:
        top = np.argsort(-scores)[:MAX_CANDIDATES]
        boxes, scores, class_ids = boxes[top], scores[top], class_ids[top]
    return _xywh_to_xyxy(boxes), scores, class_ids


def iou_one_to_many(box: np.ndarray, boxes: np.ndarray, pixel: float = 0.0) -> np.ndarray:
    """IoU of one xyxy box with each of `boxes`.

    `pixel` is added to every width and height, for toolchains that count box edges as
    whole pixels: YOLOX's demo NMS takes x2 - x1 + 1 in image pixels, which is `pixel` = r
    on boxes in model-input pixels (r: the letterbox scale).
    """
    x1 = np.maximum(box[0], boxes[:, 0])
    y1 = np.maximum(box[1], boxes[:, 1])
    x2 = np.minimum(box[2], boxes[:, 2])
    y2 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x2 - x1 + pixel, 0, None) * np.clip(y2 - y1 + pixel, 0, None)
    area = (box[2] - box[0] + pixel) * (box[3] - box[1] + pixel)
    areas = (boxes[:, 2] - boxes[:, 0] + pixel) * (boxes[:, 3] - boxes[:, 1] + pixel)
    return np.asarray(inter / np.maximum(area + areas - inter, 1e-9))


def nms(
    boxes: np.ndarray,
    scores: np.ndarray,
    class_ids: np.ndarray,
    iou: float,
    max_det: int = 300,
    agnostic: bool = False,
    pixel: float = 0.0,
) -> np.ndarray:
    """Greedy NMS, per class unless `agnostic`; indices of kept boxes, best score first.

    Per class is what Ultralytics and YOLOv5 do; YOLOX's ONNX demo (multiclass_nms) is
    class-agnostic by default. `pixel`: see iou_one_to_many.
    """
    if len(scores) == 0:
        return np.zeros(0, dtype=np.int64)
    shifted = boxes.astype(np.float64)
    if not agnostic:
        # Offsetting each class into its own region makes boxes of different classes disjoint.
        span = float(np.abs(boxes).max()) + 1.0 + pixel
        shifted = shifted + (class_ids.astype(np.float64) * 2.0 * span)[:, None]
    order = np.argsort(-scores, kind="stable")
    kept: list[int] = []
    while order.size and len(kept) < max_det:
        i = int(order[0])
        kept.append(i)
        rest = order[1:]
        order = rest[iou_one_to_many(shifted[i], shifted[rest], pixel) <= iou]
    return np.asarray(kept, dtype=np.int64)
