"""mono_ir: an ONNX object detector (YOLOv8/YOLO11, YOLOv5 or YOLOX layout) on the left image.

Works with the packaged demo crab detector and with any model exported from those
toolchains: input size, labels and colour order come from params, else the model.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from typing import Annotated, Any, Literal

import msgspec
import numpy as np
from trapflow_workers.common import check_frame, load_labels, model_path, parse_params
from trapflow_workers.onnx_session import ModelParams, Session, open_session
from trapflow_workers.yolo_decode import (
    DEFAULT_STRIDES,
    Layout,
    check_layout,
    decode,
    detect_layout,
    letterbox,
    nms,
)

from trapflow.errors import WorkerError
from trapflow.messages import Detection, MonoIR
from trapflow.plugin import Context, Pair, Worker

log = logging.getLogger(__name__)

Unit = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
Side = Annotated[int, msgspec.Meta(ge=16, le=4096)]


class DetectorParams(ModelParams):
    """`pools.mono.params`: every key is optional (empty model: the packaged one)."""

    layout: Literal["auto", "yolov8", "yolov5", "yolox"] = "auto"
    """Output decoder; auto chooses from the output shape."""
    confidence: Unit = 0.25
    """Detections below this score are dropped."""
    iou: Unit = 0.45
    """NMS IoU threshold (per class)."""
    max_detections: Annotated[int, msgspec.Meta(ge=1, le=1000)] = 100
    input_size: tuple[Side, Side] | None = None
    """(height, width) for models with a dynamic input; default: the model's, else 640x640."""
    color: Literal["auto", "rgb", "bgr"] = "auto"
    """Channel order fed to the model; auto = metadata `color_order`, else bgr for yolox, rgb."""
    scale: float | None = None
    """Pixel multiplier; default: metadata `scale`, else 1 for yolox and 1/255 otherwise."""
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Subtracted after scaling (in the model's channel order)."""
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Divided after subtracting the mean."""
    strides: tuple[int, ...] = DEFAULT_STRIDES
    """Head strides for yolox grid decoding."""
    image: Literal["left", "right"] = "left"
    """Which image of the pair to analyse."""


def _metadata_size(meta: Mapping[str, str]) -> tuple[int, int] | None:
    raw = meta.get("imgsz")
    if not raw:
        return None
    try:
        val = json.loads(raw)
    except json.JSONDecodeError:
        return None
    if isinstance(val, int):
        return (val, val)
    if isinstance(val, list) and len(val) == 2 and all(isinstance(v, int) for v in val):
        return (val[0], val[1])
    return None


class CrabDetector(Worker):
    """Letterbox -> ONNX model -> decoder -> class-aware NMS -> boxes in image pixels."""

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        p = parse_params(params, DetectorParams, ctx.pool)
        self.p = p
        path = model_path(p.model, "crab_detector.onnx")
        self.session: Session = open_session(path, p.providers, p.threads)
        meta = self.session.metadata
        inp = self.session.inputs[0]
        shape = list(inp.shape)
        if len(shape) != 4:
            raise WorkerError(f"model {path.name}: expected a 4-D image input, got shape {shape}")
        self.nhwc = shape[3] == 3 and shape[1] != 3
        hw = shape[1:3] if self.nhwc else shape[2:4]
        static = tuple(hw) if all(isinstance(v, int) and v > 0 for v in hw) else None
        if p.input_size and static and tuple(p.input_size) != static:
            raise WorkerError(
                f"pools.{ctx.pool}.params.input_size: model {path.name} has a fixed "
                f"input of {static[0]}x{static[1]}, got {p.input_size[0]}x{p.input_size[1]}"
            )
        size = p.input_size or static or _metadata_size(meta) or (640, 640)
        self.input_hw: tuple[int, int] = (int(size[0]), int(size[1]))
        self.input_name = inp.name
        self.dtype = self.session.input_dtype()
        self.labels = load_labels(p.labels, path, meta)
        self.layout = self._probe_layout(path.name, meta)
        color = p.color if p.color != "auto" else meta.get("color_order", "").lower()
        if color not in ("rgb", "bgr"):
            color = "bgr" if self.layout == "yolox" else "rgb"
        self.rgb = color == "rgb"
        if p.scale is not None:
            self.scale = p.scale
        elif "scale" in meta:
            self.scale = float(meta["scale"])
        else:
            self.scale = 1.0 if self.layout == "yolox" else 1.0 / 255.0
        self.mean = np.asarray(p.mean, np.float32).reshape(3, 1, 1)
        self.std = np.asarray(p.std, np.float32).reshape(3, 1, 1)
        log.info(
            "detector %s: layout %s, input %dx%d, %s, %d classes",
            path.name,
            self.layout,
            self.input_hw[1],
            self.input_hw[0],
            color,
            self.nc,
        )

    def _probe_layout(self, name: str, meta: Mapping[str, str]) -> Layout:
        """Run the model once on a blank input: the output shape fixes the decoder."""
        out = self.session.run(
            {self.input_name: self._blob(np.full((*self.input_hw, 3), 114, np.uint8), probe=True)}
        )[0]
        shape = tuple(int(v) for v in out.shape)
        forced = self.p.layout if self.p.layout != "auto" else meta.get("layout", "auto")
        nc = len(self.labels) if self.labels else None
        if forced in ("yolov8", "yolov5", "yolox"):
            layout: Layout = forced
        else:
            layout = detect_layout(shape, self.input_hw, nc, self.p.strides)
        self.nc = check_layout(layout, shape, self.input_hw, self.p.strides)
        if nc is not None and nc != self.nc:
            raise WorkerError(
                f"model {name}: output {list(shape)} has {self.nc} classes "
                f"for layout {layout}, but {nc} labels are given"
            )
        return layout

    def _blob(self, img: np.ndarray, probe: bool = False) -> np.ndarray:
        if not probe and self.rgb:
            img = img[:, :, ::-1]
        x = img.transpose(2, 0, 1).astype(np.float32) * np.float32(self.scale if not probe else 1.0)
        if not probe:
            x = (x - self.mean) / self.std
        if self.nhwc:
            x = x.transpose(1, 2, 0)
        return np.ascontiguousarray(x[None], dtype=self.dtype)

    def process(self, pair: Pair) -> MonoIR:
        check_frame(pair)
        image = pair.left if self.p.image == "left" else pair.right
        boxed, lb = letterbox(image, self.input_hw)
        out = self.session.run({self.input_name: self._blob(boxed)})[0]
        boxes, scores, ids = decode(
            out, self.layout, self.p.confidence, self.input_hw, self.p.strides
        )
        keep = nms(boxes, scores, ids, self.p.iou, self.p.max_detections)
        mapped = lb.to_image(boxes[keep], image.shape[1], image.shape[0])
        dets = [
            Detection(
                label=self._label(int(ids[k])),
                confidence=float(scores[k]),
                box=(float(b[0]), float(b[1]), float(b[2]), float(b[3])),
            )
            for k, b in zip(keep, mapped, strict=True)
        ]
        return MonoIR(detections=dets)

    def _label(self, cls: int) -> str:
        return self.labels[cls] if self.labels else f"class{cls}"

    def cleanup(self) -> None:
        self.session = None
