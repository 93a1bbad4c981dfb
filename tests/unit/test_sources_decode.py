"""Strict decoding for finite sources: what OpenCV would accept silently is a skipped pair."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from trapflow.sources.base import SkipPair
from trapflow.sources.decode import decode_bgr, same_size

IMG = np.random.default_rng(5).integers(0, 255, (48, 64, 3), dtype=np.uint8)
JPEG = cv2.imencode(".jpg", IMG)[1].tobytes()
PNG = cv2.imencode(".png", IMG)[1].tobytes()


def test_opencv_reads_a_cut_jpeg_file_silently(tmp_path: Path) -> None:
    """Regression (issue 12, item 2): a JPEG file cut short ("Premature end of JPEG file")
    was read by cv2.imread as a partly grey image; decode_bgr rejects the same bytes."""
    path = tmp_path / "cut.jpg"
    path.write_bytes(JPEG[: len(JPEG) // 2])
    partial = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert partial is not None and partial.shape == IMG.shape
    with pytest.raises(SkipPair, match="cut short"):
        decode_bgr(path.read_bytes(), str(path))


@pytest.mark.parametrize(
    ("data", "kind", "error"),
    [
        (b"", "unreadable", "empty \\(0 bytes\\)"),
        (b"not an image" * 20, "unreadable", "240 bytes that no image decoder accepts"),
        (JPEG[: len(JPEG) // 2], "truncated", "JPEG of .* has no end marker \\(FF D9\\)"),
        (JPEG[:-2], "truncated", "JPEG of .* has no end marker"),
        (PNG[: len(PNG) - 20], "truncated", "PNG of .* has no IEND chunk"),
        (JPEG[:2] + b"\0" * 300 + JPEG[-2:], "unreadable", "304 bytes that no image decoder"),
    ],
    ids=["empty", "garbage", "jpeg-half", "jpeg-no-eoi", "png-cut", "jpeg-markers-only"],
)
def test_bad_images_are_skipped_with_their_kind(data: bytes, kind: str, error: str) -> None:
    with pytest.raises(SkipPair, match=f"left/000007.jpg: {error}") as info:
        decode_bgr(data, "left/000007.jpg")
    assert info.value.kind == kind


@pytest.mark.parametrize(
    "data",
    [JPEG, PNG, JPEG + b"\0" * 512],  # zero padding after EOI (sector-sized writes)
    ids=["jpeg", "png", "jpeg-padded"],
)
def test_complete_images_decode(data: bytes) -> None:
    out = decode_bgr(data, "x")
    ref = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert out.shape == IMG.shape and np.array_equal(out, ref)


@pytest.mark.parametrize(
    ("right", "ok"),
    [(lambda: IMG, True), (lambda: IMG[:40], False), (lambda: IMG[:, :, :1], False)],
)
def test_pairs_of_two_sizes_are_skipped(right: Callable[[], np.ndarray], ok: bool) -> None:
    if ok:
        same_size(IMG, right(), "pair 3")
        return
    with pytest.raises(SkipPair, match="pair 3: left is 64x48, right is") as info:
        same_size(IMG, right(), "pair 3")
    assert info.value.kind == "size"
