"""What happens to one pair at a pool, with no process around it: decode the frames as the
plugin wants them, run the plugin, build the result. A worker (trapflow.pools.worker) and
a batch chunk (trapflow.batch.chunk) both call process_pair, so a result is made one way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import cv2
import msgspec
import numpy as np

from trapflow.errors import ProtocolError
from trapflow.plugin import Pair, Worker
from trapflow.tracking.review import sharpness
from trapflow.wire import jpeg, messages

# Result bodies that depend on the stereo geometry, stamped with the rig's id.
STAMPED = (messages.StereoIR, messages.StereoVO, messages.Tags)
# What a decoded pair depends on: images at all, their colour, the largest size wanted.
Need = tuple[bool, str, tuple[int, int] | None]


def decode_image(frame: Any, pair: messages.StereoPair, side: str,
                 grey: bool = False, reduce: int = 1) -> np.ndarray:
    """A BGR uint8 image from a JPEG or raw frame (or ring view), grey (HxW) from a JPEG when
    the plugin asks for grey, and a JPEG decoded at 1/reduce of its size (a raw frame stays
    whole); ProtocolError if not one."""
    buf = _as_bytes(frame)
    if pair.encoding == "raw":
        return buf.reshape(pair.height, pair.width, 3)
    # libjpeg-turbo (simplejpeg), OpenCV as the fallback
    img = jpeg.decode(buf, grey=grey, reduce=reduce)
    if img is None:
        raise ProtocolError(f"pair {pair.seq}: {side} image is not a decodable JPEG "
                            f"({buf.size} bytes)")
    width, height = jpeg.reduced_size((pair.width, pair.height), reduce)
    if img.shape[:2] != (height, width):
        at = f" (the header's {pair.width}x{pair.height} at 1/{reduce})" if reduce > 1 else ""
        raise ProtocolError(
            f"pair {pair.seq}: {side} image expected {width}x{height}{at}, "
            f"got {img.shape[1]}x{img.shape[0]}"
        )
    return img


def decode_pair(plugin: Worker, header: messages.StereoPair, left: Any, right: Any,
                gap: int = 0) -> Pair:
    """The pair as `plugin` wants it: decoded in its colour and, for a JPEG, at the largest
    DCT reduction its max_size allows; the encoded bytes when it needs no images."""
    if not plugin.needs_images:  # the encoded bytes, zero-copy: plugins that never look
        return Pair(header=header, left=_as_bytes(left), right=_as_bytes(right), gap=gap)
    grey = plugin.colour == "grey"
    reduce = 1 if header.encoding == "raw" else jpeg.scale_for(
        (header.width, header.height), plugin.max_size)
    return Pair(header=header, left=decode_image(left, header, "left", grey, reduce),
                right=decode_image(right, header, "right", grey, reduce), gap=gap,
                reduction=reduce)


def _as_bytes(frame: Any) -> np.ndarray:
    if isinstance(frame, np.ndarray):
        return frame.reshape(-1)  # a view of a contiguous frame
    return np.frombuffer(frame.buffer if hasattr(frame, "buffer") else frame, dtype=np.uint8)


def to_frame_pixels(body: messages.Body, reduction: int, width: int, height: int
                    ) -> messages.Body:
    """A body a plugin computed on images reduced by `reduction` (its max_size), in the
    frame's pixels: boxes scaled (image pixel x is frame pixel x * reduction) and kept
    inside the frame, disparities scaled alike. Metric fields (range, length, position)
    do not depend on the pixel size and stay as they are."""
    if not isinstance(body, messages.MonoIR) or not body.detections:
        return body
    r = float(reduction)
    dets = [msgspec.structs.replace(
        d, box=(min(d.box[0] * r, width), min(d.box[1] * r, height),
                min(d.box[2] * r, width), min(d.box[3] * r, height)),
        disparity_px=None if d.disparity_px is None else d.disparity_px * r)
        for d in body.detections]
    return msgspec.structs.replace(body, detections=dets)


@dataclass(frozen=True)
class ViewSpec:
    """Which boxes a detector's worker crops for the review queue's best views: those at
    or above `min_confidence` (tracks start there), the `most` most confident of a pair,
    each with its longest side at most `crop_px`, as a JPEG of `quality`."""

    min_confidence: float
    crop_px: int
    most: int = 2
    quality: int = 85
    min_px: int = 8  # a box smaller than this on a side is no view
    every_s: float = 1.0  # a worker sends crops with at most one pair a second (ViewPacer)


class ViewPacer:
    """Which pairs a worker crops: one a `every_s` of capture time at most, so crops (tens
    of kilobytes) stay a small share of what results carry to the normalizer; a pair that
    brought none leaves the next one due. Capture time, never the wall clock; a clock that
    went back (a replay started again) makes the next pair due."""

    def __init__(self, spec: ViewSpec) -> None:
        self.spec = spec
        self.next_ns: int | None = None

    @staticmethod
    def _t(header: messages.StereoPair) -> int:
        return header.t_wall_ns if header.source_time else header.t_mono_ns

    def due(self, header: messages.StereoPair) -> ViewSpec | None:
        """The spec when this pair's boxes are to be cropped, else None."""
        t, nxt = self._t(header), self.next_ns
        every = int(self.spec.every_s * 1e9)
        return self.spec if nxt is None or t >= nxt or t < nxt - every else None

    def done(self, header: messages.StereoPair, body: messages.Body) -> None:
        """The pair's result: crops sent make the next pair due `every_s` later."""
        if isinstance(body, messages.MonoIR) and body.views:
            self.next_ns = self._t(header) + int(self.spec.every_s * 1e9)


def crop_views(body: messages.Body, pair: Pair, spec: ViewSpec) -> messages.Body:
    """A detector's body (its boxes in frame pixels) with the crops of its confident boxes
    from the pair's decoded left image, taken now that the worker holds the pixels (a pair
    leaves the frame ring before its result reaches the normalizer); unchanged when it is
    no detector's, or has no box to crop, or the plugin took no images."""
    if (not isinstance(body, messages.MonoIR) or not isinstance(pair.left, np.ndarray)
            or pair.left.ndim < 2):  # a plugin without images gets the encoded bytes
        return body
    img, r = pair.left, float(pair.reduction)
    h, w = img.shape[:2]
    dets = sorted((d for d in body.detections if d.confidence >= spec.min_confidence),
                  key=lambda d: -d.confidence)[:spec.most]
    views = []
    for d in dets:
        x1, y1 = max(0, int(d.box[0] / r)), max(0, int(d.box[1] / r))
        x2, y2 = min(w, int(np.ceil(d.box[2] / r))), min(h, int(np.ceil(d.box[3] / r)))
        if x2 - x1 < spec.min_px or y2 - y1 < spec.min_px:
            continue
        crop = img[y1:y2, x1:x2]
        scale = spec.crop_px / max(crop.shape[:2])
        if scale < 1:
            crop = cv2.resize(crop, (max(1, round(crop.shape[1] * scale)),
                                     max(1, round(crop.shape[0] * scale))),
                              interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".jpg", crop, [cv2.IMWRITE_JPEG_QUALITY, spec.quality])
        if ok:
            views.append(messages.BoxView(box=d.box, jpeg=buf.tobytes(),
                                          sharpness=round(sharpness(crop), 2)))
    return msgspec.structs.replace(body, views=views) if views else body


@dataclass(frozen=True)
class Processed:
    """A pair through a plugin: the pair as decoded, its result, and the CPU time (all
    threads) the plugin spent on it."""

    pair: Pair
    result: messages.Result
    cpu_ns: int


def process_pair(plugin: Worker, header: messages.StereoPair, left: Any, right: Any, *,
                 pool: str, worker: str, calib: str, gap: int = 0,
                 decoded: dict[Need, Pair] | None = None,
                 views: ViewSpec | None = None) -> Processed:
    """Decode the pair for `plugin` (or take it from `decoded`: this pair decoded already
    for other plugins, by what they needed), run the plugin, and build the result; a
    stereo result is stamped with `calib`, the id of the rig it was computed with; with
    `views`, a detector's confident boxes carry their crops (crop_views). Raises
    whatever decoding or the plugin raised: the caller fails that one pair."""
    need = (plugin.needs_images, plugin.colour, plugin.max_size)
    pair = decoded.get(need) if decoded is not None else None
    if pair is None:
        pair = decode_pair(plugin, header, left, right, gap)
        if decoded is not None:
            decoded[need] = pair
    t0, c0 = time.monotonic_ns(), time.process_time_ns()
    body = plugin.process(pair)
    proc_ns = time.monotonic_ns() - t0
    cpu_ns = time.process_time_ns() - c0
    if pair.reduction > 1:
        body = to_frame_pixels(body, pair.reduction, header.width, header.height)
    if isinstance(body, STAMPED) and not body.calib:
        body = msgspec.structs.replace(body, calib=calib)
    if views is not None:
        body = crop_views(body, pair, views)
    result = messages.Result(seq=header.seq, t_wall_ns=header.t_wall_ns,
                             t_mono_ns=header.t_mono_ns, pool=pool, worker=worker,
                             proc_ns=proc_ns, body=body, source_time=header.source_time)
    return Processed(pair=pair, result=result, cpu_ns=cpu_ns)
