"""Detector input as each YOLO toolchain prepares it: letterbox geometry and the input tensor.

Two placements, one per toolchain:
  center   Ultralytics YOLOv5 / YOLOv8 / YOLO11 `LetterBox(auto=False, center=True)`: size
           w*r, h*r rounded, padding split around the image (top = round(dh - 0.1)).
  topleft  YOLOX `preproc`: size w*r, h*r truncated, image at [0:h', 0:w'], padding at
           the bottom and right.
with r = min(H/h, W/w) in both; boxes map back as (xy - pad) / r.

Preprocessor owns the one input tensor a detector feeds its model: the padding is written
when the frame size changes, each frame only its image region, in one pass per pixel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

Placement = Literal["center", "topleft"]
PLACEMENTS: tuple[Placement, ...] = ("center", "topleft")
PAD_VALUE = 114  # grey; Ultralytics and YOLOX both pad with it


@dataclass(frozen=True)
class Letterbox:
    """How an image was fitted into the model input: scale r, resized size, padding left/top."""

    scale: float
    pad_x: int
    pad_y: int
    width: int
    height: int

    def to_image(self, boxes: np.ndarray, width: int, height: int) -> np.ndarray:
        """Map xyxy boxes from model input pixels back to the original image, clipped."""
        out = boxes.astype(np.float64, copy=True)
        out[:, [0, 2]] = (out[:, [0, 2]] - self.pad_x) / self.scale
        out[:, [1, 3]] = (out[:, [1, 3]] - self.pad_y) / self.scale
        out[:, [0, 2]] = out[:, [0, 2]].clip(0, width)
        out[:, [1, 3]] = out[:, [1, 3]].clip(0, height)
        return out


def fit(height: int, width: int, size: tuple[int, int], placement: Placement) -> Letterbox:
    """Where a height x width image goes inside an input of size (H, W)."""
    th, tw = size
    r = min(th / height, tw / width)
    if placement == "center":
        nw, nh = max(1, round(width * r)), max(1, round(height * r))
        left, top = round((tw - nw) / 2 - 0.1), round((th - nh) / 2 - 0.1)
    else:
        nw, nh = max(1, int(width * r)), max(1, int(height * r))
        left = top = 0
    return Letterbox(scale=r, pad_x=left, pad_y=top, width=nw, height=nh)


def letterbox(
    image: np.ndarray,
    size: tuple[int, int],
    fill: int = PAD_VALUE,
    placement: Placement = "center",
) -> tuple[np.ndarray, Letterbox]:
    """The padded uint8 image of size (H, W) and its geometry (a copy; Preprocessor avoids it)."""
    lb = fit(image.shape[0], image.shape[1], size, placement)
    out = np.full((*size, image.shape[2]), fill, np.uint8)
    if (lb.width, lb.height) != (image.shape[1], image.shape[0]):
        image = cv2.resize(image, (lb.width, lb.height), interpolation=cv2.INTER_LINEAR)
    out[lb.pad_y : lb.pad_y + lb.height, lb.pad_x : lb.pad_x + lb.width] = image
    return out, lb


def allocate_tensor(
    image: np.ndarray,
    size: tuple[int, int],
    placement: Placement,
    fill: int,
    rgb: bool,
    scale: float,
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0),
    std: tuple[float, float, float] = (1.0, 1.0, 1.0),
    nhwc: bool = False,
) -> tuple[np.ndarray, Letterbox]:
    """The float32 input tensor the straightforward way, new arrays at every step (a padded
    copy, a channel swap, a float copy, a division): what Preprocessor must equal bit for
    bit, and the baseline benchmarks/algorithms.py times it against."""
    boxed, lb = letterbox(image, size, fill, placement)
    x = boxed[:, :, ::-1] if rgb else boxed
    x = x.transpose(2, 0, 1).astype(np.float32)
    div = _divisor(scale)
    x = x / np.float32(div) if div is not None else x * np.float32(scale)
    if tuple(mean) != (0.0, 0.0, 0.0) or tuple(std) != (1.0, 1.0, 1.0):
        x = ((x - np.asarray(mean, np.float32).reshape(3, 1, 1))
             / np.asarray(std, np.float32).reshape(3, 1, 1))
    x = x[None]
    return (np.ascontiguousarray(x.transpose(0, 2, 3, 1)) if nhwc else x), lb


def _divisor(scale: float) -> float | None:
    """1/scale when it is a whole number: toolchains divide by 255, and so must we, bit for bit."""
    if scale <= 0.0:
        return None
    inv = 1.0 / scale
    return float(round(inv)) if round(inv) > 1 and abs(inv - round(inv)) < 1e-6 else None


class Preprocessor:
    """BGR uint8 frame -> the model's input tensor, written in place into one reusable buffer.

    The returned tensor is overwritten by the next call: run the model on it before then.
    """

    def __init__(
        self,
        input_hw: tuple[int, int],
        placement: Placement,
        fill: int,
        rgb: bool,
        scale: float,
        mean: tuple[float, float, float] = (0.0, 0.0, 0.0),
        std: tuple[float, float, float] = (1.0, 1.0, 1.0),
        nhwc: bool = False,
        dtype: type[np.floating] = np.float32,
    ) -> None:
        h, w = input_hw
        self.input_hw = (h, w)
        self.placement: Placement = placement
        self.fill = fill
        self.rgb = rgb
        self.scale = scale
        self._divisor = _divisor(scale)
        self._normalise = tuple(mean) != (0.0, 0.0, 0.0) or tuple(std) != (1.0, 1.0, 1.0)
        self._mean = np.asarray(mean, dtype).reshape(3, 1, 1)
        self._std = np.asarray(std, dtype).reshape(3, 1, 1)
        self.tensor = np.empty((1, h, w, 3) if nhwc else (1, 3, h, w), dtype)
        # Channel-first view of the tensor whatever its memory layout.
        self._chw = self.tensor[0].transpose(2, 0, 1) if nhwc else self.tensor[0]
        self._frame_hw: tuple[int, int] | None = None
        self._lb = fit(1, 1, input_hw, placement)
        self._region = self._chw
        self._resized = np.empty((0, 0, 3), np.uint8)

    def _convert(self, chw_u8: np.ndarray, out: np.ndarray) -> None:
        """Scale uint8 channel-first pixels (model channel order) into `out`, in one pass."""
        if self._divisor is not None:
            np.divide(chw_u8, out.dtype.type(self._divisor), out=out)
        else:
            np.multiply(chw_u8, out.dtype.type(self.scale), out=out)
        if self._normalise:
            out -= self._mean
            out /= self._std

    def _reset(self, height: int, width: int) -> None:
        lb = fit(height, width, self.input_hw, self.placement)
        pad = np.empty((3, 1, 1), self.tensor.dtype)
        self._convert(np.full((3, 1, 1), self.fill, np.uint8), pad)
        self._chw[...] = pad
        self._region = self._chw[:, lb.pad_y : lb.pad_y + lb.height, lb.pad_x : lb.pad_x + lb.width]
        self._resized = np.empty((lb.height, lb.width, 3), np.uint8)
        self._lb = lb
        self._frame_hw = (height, width)

    def __call__(self, image: np.ndarray) -> tuple[np.ndarray, Letterbox]:
        """The input tensor for `image` (HxWx3 BGR uint8) and where the image went in it."""
        h, w = image.shape[:2]
        if (h, w) != self._frame_hw:
            self._reset(h, w)
        lb = self._lb
        src = image
        if (lb.width, lb.height) != (w, h):
            src = cv2.resize(
                image, (lb.width, lb.height), dst=self._resized, interpolation=cv2.INTER_LINEAR
            )
        chw = src.transpose(2, 0, 1)
        self._convert(chw[::-1] if self.rgb else chw, self._region)
        return self.tensor, lb
