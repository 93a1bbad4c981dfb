"""mono_ir: an ONNX object detector (YOLOv8/YOLO11, YOLOv5 or YOLOX layout) on the left image.

Works with the packaged demo crab detector and with any model exported from those
toolchains: input size, labels and colour order come from params, else the model. Each
layout gets its own toolchain's pre- and post-processing unless params or metadata say
otherwise: Ultralytics (v5, v8, 11) a centred letterbox, RGB, /255 and per-class NMS;
YOLOX the image at the top-left, BGR, no scaling and class-agnostic NMS (its ONNX demo).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, Literal, cast

import cv2
import msgspec
import numpy as np

from trapflow.plugin import (
    Context,
    Detection,
    Measured,
    MonoIR,
    Pair,
    StereoRig,
    Worker,
    WorkerError,
    check_frame,
    measure,
    pair_floor,
    parse_params,
)

from .common import load_labels, model_path
from .onnx_session import ModelParams, Session, open_session
from .yolo_decode import (
    DEFAULT_STRIDES,
    LAYOUTS,
    Layout,
    check_layout,
    decode,
    detect_layout,
    nms,
)
from .yolo_preprocess import PAD_VALUE, PLACEMENTS, Placement, Preprocessor, fit

log = logging.getLogger(__name__)

Unit = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
Side = Annotated[int, msgspec.Meta(ge=16, le=4096)]


#: the packaged demo models, by `variant`
VARIANTS = {"fp32": "crab_detector.onnx", "int8": "crab_detector_int8.onnx"}
#: the packaged model run when `variant` is empty: int8, whose crab mAP@0.5 on held-out
#: synthetic worlds is within 0.02 of fp32's (0.801 vs 0.800, models/crab_detector.md; the
#: bench measures both in one run) at 0.54x its time per inference
DEFAULT_VARIANT = "int8"


class DetectorParams(ModelParams):
    """`pools.mono.params`: every key is optional (empty model: the packaged one)."""

    variant: Literal["", "fp32", "int8"] = ""
    """Which packaged demo model runs when `model` is empty: fp32, or its int8 quantization
    (static QDQ; accuracy and speed of both in models/crab_detector.md); empty = int8."""
    layout: Literal["auto", "yolov8", "yolov5", "yolox", "yolox_decoded"] = "auto"
    """Output decoder; auto = metadata `layout`, else chosen from the output shape (and for
    YOLOX from its values: raw grid offsets or boxes decoded in the graph)."""
    confidence: Unit = 0.25
    """Detections at or below this score are dropped."""
    iou: Unit = 0.45
    """NMS IoU threshold."""
    agnostic_nms: bool | None = None
    """NMS across classes; default: true for YOLOX (its ONNX demo), false otherwise."""
    max_detections: Annotated[int, msgspec.Meta(ge=1, le=1000)] = 100
    input_size: tuple[Side, Side] | None = None
    """(height, width) for models with a dynamic input; default: the model's, else 640x640."""
    letterbox: Literal["auto", "center", "topleft"] = "auto"
    """Where the resized image goes in the input; auto = metadata `letterbox`, else topleft
    for YOLOX (its preproc) and center otherwise (Ultralytics' LetterBox)."""
    pad_value: Annotated[int, msgspec.Meta(ge=0, le=255)] | None = None
    """Grey level of the padding; default: metadata `pad_value`, else 114."""
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
    measure: bool = True
    """Measure every box on the stereo pair: range, 3-D position and length with their
    uncertainty, or the reason it could not (trapflow.measure.stereo; about 1 ms a box, and
    the floor's plane once per pair with boxes, about as much).
    Boxes found in the right image (`image: right`) are not measured."""


def _metadata_choice(
    meta: Mapping[str, str], key: str, allowed: tuple[str, ...], model: str, param: str, pool: str
) -> str | None:
    """A metadata value that must be one of `allowed`; None when the key is absent."""
    raw = meta.get(key)
    if raw is None:
        return None
    value = raw.strip().lower()
    if value not in allowed:
        raise WorkerError(
            f"model {model} metadata {key!r}: expected one of {', '.join(allowed)}, got "
            f"{raw[:40]!r} (fix the metadata or set pools.{pool}.params.{param})"
        )
    return value


def _metadata_number(
    meta: Mapping[str, str], key: str, model: str, param: str, pool: str
) -> float | None:
    """A numeric metadata value; None when the key is absent."""
    raw = meta.get(key)
    if raw is None:
        return None
    try:
        return float(raw)
    except ValueError:
        raise WorkerError(
            f"model {model} metadata {key!r}: expected a number, got {raw[:40]!r} "
            f"(fix the metadata or set pools.{pool}.params.{param})"
        ) from None


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


@dataclass(frozen=True)
class InputSpec:
    """How frames become the model's input: placement, padding, channel order, scaling."""

    placement: Placement
    pad_value: int
    rgb: bool
    scale: float


def input_spec(
    p: DetectorParams, meta: Mapping[str, str], yolox: bool, model: str, pool: str
) -> InputSpec:
    """Each setting from params, else the model's metadata, else the layout's toolchain."""
    placement: str | None = p.letterbox if p.letterbox != "auto" else None
    if placement is None:
        placement = _metadata_choice(meta, "letterbox", PLACEMENTS, model, "letterbox", pool)
    color: str | None = p.color if p.color != "auto" else None
    if color is None:
        color = _metadata_choice(meta, "color_order", ("rgb", "bgr"), model, "color", pool)
    scale = p.scale
    if scale is None:
        scale = _metadata_number(meta, "scale", model, "scale", pool)
    pad = p.pad_value
    if pad is None:
        value = _metadata_number(meta, "pad_value", model, "pad_value", pool)
        if value is not None and not (0 <= value <= 255 and value == int(value)):
            raise WorkerError(
                f"model {model} metadata 'pad_value': expected an integer 0..255, got "
                f"{meta['pad_value'][:40]!r} (fix the metadata or set "
                f"pools.{pool}.params.pad_value)"
            )
        pad = None if value is None else int(value)
    return InputSpec(
        placement=cast(Placement, placement or ("topleft" if yolox else "center")),
        pad_value=PAD_VALUE if pad is None else pad,
        rgb=(color or ("bgr" if yolox else "rgb")) == "rgb",
        scale=(1.0 if yolox else 1.0 / 255.0) if scale is None else scale,
    )


class CrabDetector(Worker):
    """Letterbox -> ONNX model -> decoder -> NMS -> boxes in image pixels, as the toolchain does."""

    reconfigurable = True  # configure() opens a new session; nothing else is kept

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        p = parse_params(params, DetectorParams, ctx.pool)
        self.p = p
        self.ctx_rig = ctx.rig
        if p.model and p.variant == "int8":
            raise WorkerError(
                f"pools.{ctx.pool}.params.variant: {p.variant!r} picks a packaged demo model, "
                f"but model is set ({p.model}): drop variant, or drop model to run the packaged "
                f"{p.variant} one"
            )
        path = model_path(p.model, VARIANTS[p.variant or DEFAULT_VARIANT])
        self.session: Session = open_session(path, p.providers, p.threads, settings=p)
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
        dtype = self.session.input_dtype()
        self.labels = load_labels(p.labels, path, meta)
        self.layout = self._probe_layout(path.name, meta, dtype, ctx.pool)
        yolox = self.layout.startswith("yolox")
        spec = input_spec(p, meta, yolox, path.name, ctx.pool)
        self.agnostic = p.agnostic_nms if p.agnostic_nms is not None else yolox
        # YOLOX's demo NMS counts box edges as whole pixels (x2 - x1 + 1).
        self.edge_pixel = yolox
        self.preprocess = Preprocessor(
            self.input_hw,
            placement=spec.placement,
            fill=spec.pad_value,
            rgb=spec.rgb,
            scale=spec.scale,
            mean=p.mean,
            std=p.std,
            nhwc=self.nhwc,
            dtype=dtype,
        )
        # The largest image the letterbox keeps of the run's frames: a JPEG is decoded at
        # the DCT scale that still covers it (1280x720 into 320x320: 320x180, 1/4).
        fitted = fit(ctx.rig.height, ctx.rig.width, self.input_hw, spec.placement)
        self.max_size = (fitted.width, fitted.height)
        self._log_setup(path.name, spec, self.max_size)

    def _log_setup(self, model: str, spec: InputSpec, covered: tuple[int, int]) -> None:
        """One line of what configure() settled on."""
        log.info(
            "detector %s: layout %s, input %dx%d, letterbox %s pad %d, %s, scale %.6g, "
            "%s NMS, %d classes, JPEG decoded to cover %dx%d",
            model,
            self.layout,
            self.input_hw[1],
            self.input_hw[0],
            spec.placement,
            spec.pad_value,
            "rgb" if spec.rgb else "bgr",
            spec.scale,
            "class-agnostic" if self.agnostic else "per-class",
            self.nc,
            *covered,
        )

    def _probe_layout(
        self, name: str, meta: Mapping[str, str], dtype: type[np.floating], pool: str
    ) -> Layout:
        """Run the model once on a blank grey input: the output fixes the decoder."""
        h, w = self.input_hw
        blank = np.full((1, h, w, 3) if self.nhwc else (1, 3, h, w), PAD_VALUE, dtype)
        out = self.session.run({self.input_name: blank})[0]
        shape = tuple(int(v) for v in out.shape)
        forced: str | None = self.p.layout if self.p.layout != "auto" else None
        if forced is None:
            forced = _metadata_choice(meta, "layout", LAYOUTS, name, "layout", pool)
        nc = len(self.labels) if self.labels else None
        if forced:
            layout = cast(Layout, forced)
        else:
            layout = detect_layout(shape, self.input_hw, nc, self.p.strides, sample=out)
        self.nc = check_layout(layout, shape, self.input_hw, self.p.strides)
        if nc is not None and nc != self.nc:
            raise WorkerError(
                f"model {name}: output {list(shape)} has {self.nc} classes "
                f"for layout {layout}, but {nc} labels are given"
            )
        return layout

    def process(self, pair: Pair) -> MonoIR:
        check_frame(pair)
        image = pair.left if self.p.image == "left" else pair.right
        tensor, lb = self.preprocess(image)
        out = self.session.run({self.input_name: tensor})[0]
        boxes, scores, ids = decode(
            out, self.layout, self.p.confidence, self.input_hw, self.p.strides
        )
        keep = nms(
            boxes,
            scores,
            ids,
            self.p.iou,
            self.p.max_detections,
            agnostic=self.agnostic,
            # one frame pixel, in input pixels (an image reduced by r has r-pixel pixels)
            pixel=lb.scale / pair.reduction if self.edge_pixel else 0.0,
        )
        # In the image's pixels: the runtime maps a reduced image's boxes to the frame's.
        mapped = lb.to_image(boxes[keep], image.shape[1], image.shape[0])
        dets = [
            Detection(
                label=self._label(int(ids[k])),
                confidence=float(scores[k]),
                box=(float(b[0]), float(b[1]), float(b[2]), float(b[3])),
            )
            for k, b in zip(keep, mapped, strict=True)
        ]
        if dets and self.p.measure and self.p.image == "left":
            dets = self._measure(pair, dets)
        return MonoIR(detections=dets, model=self.session.model_hash)

    def _measure(self, pair: Pair, dets: list[Detection]) -> list[Detection]:
        """Each box measured on the pair (images as they came: reduced ones with the rig
        reduced alike; boxes and disparities in the image's pixels, as the runtime expects)."""
        grey = [img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
                for img in (pair.left, pair.right)]
        rig = self.rig_at(grey[0].shape[1], grey[0].shape[0])
        floor = pair_floor(grey[0], grey[1], rig)  # the slant every box on the floor shares
        out = []
        for d in dets:
            m = measure(grey[0], grey[1], rig, d.box, floor=floor)
            if isinstance(m, Measured):
                out.append(msgspec.structs.replace(
                    d, range_m=m.range_m, range_sd_m=m.range_sd_m, xyz=m.xyz,
                    disparity_px=m.disparity_px, length_m=m.length_m,
                    length_sd_m=m.length_sd_m, length_method=m.length_method))
            else:
                out.append(msgspec.structs.replace(d, unmeasured=m.reason))
        return out

    def rig_at(self, width: int, height: int) -> StereoRig:
        """The run's rig for images of this size (a reduced decode scales it)."""
        rig = self.ctx_rig
        if (width, height) == (rig.width, rig.height):
            return rig
        s = width / rig.width
        return StereoRig(width=width, height=height, fx=rig.fx * s, fy=rig.fy * s,
                         cx=(rig.cx + 0.5) * s - 0.5, cy=(rig.cy + 0.5) * s - 0.5,
                         baseline_m=rig.baseline_m)

    def _label(self, cls: int) -> str:
        return self.labels[cls] if self.labels else f"class{cls}"

    def cleanup(self) -> None:
        vars(self).pop("session", None)  # the ONNX session and its memory go now
