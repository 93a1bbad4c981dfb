"""Strict decoding of one image file or message for finite sources (folders, recordings).

OpenCV decodes a JPEG cut short ("Premature end of JPEG file") into a partly grey image
without an error, so a JPEG must end with its EOI marker and a PNG with its IEND chunk
before it is decoded. Every fault raises SkipPair: the source skips that pair and goes on.
"""

from __future__ import annotations

import cv2
import numpy as np

from trapflow.sources.base import SkipPair

JPEG_SOI, JPEG_EOI = b"\xff\xd8", b"\xff\xd9"
PNG_MAGIC, PNG_END = b"\x89PNG\r\n\x1a\n", b"IEND\xaeB`\x82"
# Some writers pad a file after its end marker with zeros (sector-sized writes on SD cards).
_TAIL = 4096


def check_complete(data: bytes, where: str) -> None:
    """SkipPair when data is empty, or a JPEG or PNG whose end marker is missing (cut short)."""
    if not data:
        raise SkipPair("unreadable", f"{where}: empty (0 bytes); expected an image")
    tail = data[-_TAIL:].rstrip(b"\x00")
    if data.startswith(JPEG_SOI) and not tail.endswith(JPEG_EOI):
        raise SkipPair("truncated", f"{where}: JPEG of {len(data)} bytes has no end marker "
                                    "(FF D9): the file was cut short")
    if data.startswith(PNG_MAGIC) and not tail.endswith(PNG_END):
        raise SkipPair("truncated", f"{where}: PNG of {len(data)} bytes has no IEND chunk: "
                                    "the file was cut short")


def decode_bgr(data: bytes, where: str) -> np.ndarray:
    """A complete encoded image as BGR uint8; SkipPair names `where` and what was wrong."""
    check_complete(data, where)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise SkipPair("unreadable", f"{where}: {len(data)} bytes that no image decoder "
                                     f"accepts (starts {data[:8].hex(' ')})")
    return img


def same_size(left: np.ndarray, right: np.ndarray, where: str) -> None:
    """SkipPair when the two images of a pair differ in size."""
    if left.shape != right.shape:
        raise SkipPair("size", f"{where}: left is {left.shape[1]}x{left.shape[0]}, right is "
                               f"{right.shape[1]}x{right.shape[0]}; expected the same size")
