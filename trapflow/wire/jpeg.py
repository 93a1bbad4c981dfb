"""JPEG where a consumer needs it: encode a raw pair once, decode with libjpeg-turbo.

On one host the ring holds raw BGR frames (decoded once at capture); JPEG is made only
by a consumer that needs it (event capture, remote pools, recorder, viewer), once per
pair. Decoding uses simplejpeg (libjpeg-turbo, in greyscale and at a reduced DCT scale
on request) and falls back to OpenCV when it is not installed. Pure functions.
"""

from __future__ import annotations

from typing import Any

import cv2
import msgspec
import numpy as np

from trapflow.wire.messages import StereoPair

try:  # libjpeg-turbo through simplejpeg: about 2x cv2.imdecode
    import simplejpeg as _sj
except ImportError:  # pragma: no cover - the OpenCV fallback
    _sj = None

# DCT scales libjpeg-turbo decodes at directly (1/8 .. 1): a factor of the full size.
_SCALES = (1, 2, 4, 8)


# The viewer's previews: small for a browser link, looked at, never analysed. The page draws
# a side at most 640 pixels wide, so a larger frame is reduced to that before encoding
# (a quarter of the pixels of 1280x720: the encode is what a preview costs the broker).
PREVIEW_QUALITY = 80
PREVIEW_WIDTH = 640


def wire_side(img: np.ndarray, encoding: str, quality: int) -> np.ndarray:
    """One side of a pair as capture sends it (and batch re-analysis feeds it): the raw
    pixels made contiguous, or one JPEG at the source's quality."""
    if encoding == "raw":
        return np.ascontiguousarray(img)
    ok, buf = cv2.imencode(".jpg", img, [int(cv2.IMWRITE_JPEG_QUALITY), quality])
    if not ok:
        raise ValueError(f"JPEG encoding of a {img.shape} image failed")
    return buf


def encode(img: np.ndarray, quality: int) -> bytes:
    """One BGR uint8 image as JPEG bytes at this quality (1..100)."""
    if _sj is not None:
        return bytes(_sj.encode_jpeg(np.ascontiguousarray(img), quality=quality,
                                     colorspace="BGR", colorsubsampling="420"))
    ok, buf = cv2.imencode(".jpg", img, [int(cv2.IMWRITE_JPEG_QUALITY), quality])
    if not ok:  # pragma: no cover - OpenCV fails only on an empty image
        raise ValueError(f"JPEG encoding of a {img.shape} image failed")
    return bytes(buf.tobytes())


def to_jpeg_pair(header: StereoPair, left: Any, right: Any,
                 quality: int) -> tuple[StereoPair, bytes, bytes]:
    """The pair as JPEG: a raw pair is encoded (both sides), a JPEG pair passes as is."""
    if header.encoding != "raw":
        return header, bytes(left), bytes(right)
    shape = (header.height, header.width, 3)
    lj, rj = (encode(np.frombuffer(b, np.uint8).reshape(shape), quality) for b in (left, right))
    return msgspec.structs.replace(header, encoding="jpeg"), lj, rj


def preview_pair(header: StereoPair, left: Any, right: Any) -> tuple[bytes, bytes]:
    """Both sides of a pair as the viewer's preview JPEGs: a raw side is reduced to at most
    PREVIEW_WIDTH wide (area average) and encoded; a JPEG side passes as it is (decoding
    it to make it smaller would cost more CPU than the bytes it saves)."""
    if header.encoding != "raw":
        return bytes(left), bytes(right)
    out = []
    for side in (left, right):
        img: np.ndarray = np.frombuffer(side, np.uint8).reshape(header.height, header.width, 3)
        if header.width > PREVIEW_WIDTH:
            size = (PREVIEW_WIDTH, max(1, round(header.height * PREVIEW_WIDTH / header.width)))
            img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        out.append(encode(img, PREVIEW_QUALITY))
    return out[0], out[1]


def scale_for(full: tuple[int, int], needed: tuple[int, int] | None) -> int:
    """The largest DCT reduction (1, 2, 4 or 8) of a full (width, height) frame that still
    covers `needed` (width, height) in both directions; 1 when nothing is needed.

    A plugin that shrinks each image to at most `needed` loses nothing it would have kept:
    the reduced frame is at least that large, and a reduction is taken only where the
    frame is twice `needed` or more.
    """
    if not needed:
        return 1
    (fw, fh), (nw, nh) = full, needed
    return max(s for s in _SCALES if s == 1 or (fw >= s * nw and fh >= s * nh))


def reduced_size(full: tuple[int, int], reduce: int) -> tuple[int, int]:
    """(width, height) of a full (width, height) JPEG decoded at 1/reduce: libjpeg rounds up."""
    return -(-full[0] // reduce), -(-full[1] // reduce)


def decode(data: Any, grey: bool = False, reduce: int = 1) -> np.ndarray | None:
    """JPEG bytes as BGR (or grey, HxW) uint8, reduced by `reduce` (1, 2, 4, 8: each side
    ceil(side / reduce), see reduced_size); None if the bytes are no decodable JPEG."""
    buf = data if isinstance(data, np.ndarray) else np.frombuffer(data, np.uint8)
    if _sj is not None:
        try:
            img = _sj.decode_jpeg(buf, colorspace="GRAY" if grey else "BGR",
                                  min_height=0, min_width=0, min_factor=1,
                                  fastdct=False, fastupsample=False) if reduce == 1 else \
                _decode_reduced(buf, grey, reduce)
        except ValueError:
            return None
        return img[:, :, 0] if grey and img.ndim == 3 else img
    flags = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
             8: cv2.IMREAD_REDUCED_COLOR_8}
    gflags = {1: cv2.IMREAD_GRAYSCALE, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2,
              4: cv2.IMREAD_REDUCED_GRAYSCALE_4, 8: cv2.IMREAD_REDUCED_GRAYSCALE_8}
    out: np.ndarray | None = cv2.imdecode(buf, (gflags if grey else flags)[reduce])
    return out


def _decode_reduced(buf: np.ndarray, grey: bool, reduce: int) -> np.ndarray:
    assert _sj is not None
    h, w = _sj.decode_jpeg_header(buf)[:2]
    rw, rh = reduced_size((w, h), reduce)
    # min_factor and the minimum size together pin libjpeg-turbo's scale to exactly
    # 1/reduce (it also offers other eighths, which OpenCV's fallback cannot match).
    img: np.ndarray = _sj.decode_jpeg(buf, colorspace="GRAY" if grey else "BGR",
                                      min_height=rh, min_width=rw, min_factor=reduce)
    return img
