"""JPEG made where a consumer needs it: libjpeg-turbo decoding agrees with OpenCV's."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests import builders
from trapflow.wire import jpeg


def _photo() -> np.ndarray:
    rng = np.random.default_rng(3)
    return cv2.GaussianBlur(rng.integers(0, 256, (240, 320, 3), dtype=np.uint8), (9, 9), 3)


@pytest.mark.parametrize(("grey", "reduce", "flag"), [
    (False, 1, cv2.IMREAD_COLOR),
    (True, 1, cv2.IMREAD_GRAYSCALE),
    (False, 2, cv2.IMREAD_REDUCED_COLOR_2),
    (True, 4, cv2.IMREAD_REDUCED_GRAYSCALE_4),
    (False, 8, cv2.IMREAD_REDUCED_COLOR_8),
])
def test_decode_matches_opencv(grey: bool, reduce: int, flag: int) -> None:
    data = cv2.imencode(".jpg", _photo(), [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
    want = cv2.imdecode(np.frombuffer(data, np.uint8), flag)
    got = jpeg.decode(data, grey=grey, reduce=reduce)
    assert got is not None and got.shape == want.shape
    assert int(np.abs(got.astype(int) - want).max()) <= 1


@pytest.mark.parametrize("data", [b"", b"x" * 100, b"\xff\xd8not-a-jpeg", b"\x89PNG\r\n\x1a\n"],
                         ids=["empty", "junk", "truncated", "png-magic"])
def test_decode_rejects_what_is_no_jpeg(data: bytes) -> None:
    assert jpeg.decode(data) is None


def test_raw_pair_becomes_jpeg_of_the_same_pixels_and_jpeg_passes_as_is() -> None:
    img = _photo()
    raw = builders.pair_header(7, 320, 240, "raw")
    header, left, right = jpeg.to_jpeg_pair(raw, img.tobytes(), img[::-1].tobytes(), 90)
    assert header.encoding == "jpeg" and header.seq == 7 and left[:2] == b"\xff\xd8"
    back = cv2.imdecode(np.frombuffer(left, np.uint8), cv2.IMREAD_COLOR)
    # Within what OpenCV's own encoder loses at the same quality (4:2:0 on a noisy image).
    ref = cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1], 1)
    loss = float(np.abs(ref.astype(float) - img).mean())
    assert float(np.abs(back.astype(float) - img).mean()) <= loss * 1.2 + 0.1
    jpg = builders.pair_header(8, 320, 240, "jpeg")
    assert jpeg.to_jpeg_pair(jpg, b"L", b"R", 90) == (jpg, b"L", b"R")


@pytest.mark.parametrize(("full", "needed", "scale"), [
    ((1280, 720), None, 1),
    ((1280, 720), (640, 360), 2),
    ((1280, 720), (320, 180), 4),  # the demo detector's letterbox of 1280x720 into 320x320
    ((1280, 720), (320, 320), 2),  # covers 320 rows: 1/2 (360), not 1/4 (180)
    ((1920, 1080), (320, 180), 4),  # 1/4 is 480x270; 1/8 (240x135) would not cover it
    ((1280, 720), (160, 90), 8),
    ((1280, 720), (641, 360), 1),  # less than twice the need: decoded whole
    ((320, 240), (640, 640), 1),
])
def test_scale_covers_the_size_a_plugin_needs(full: tuple[int, int],
                                              needed: tuple[int, int] | None,
                                              scale: int) -> None:
    assert jpeg.scale_for(full, needed) == scale
    if needed:
        w, h = jpeg.reduced_size(full, scale)
        assert w >= min(needed[0], full[0]) and h >= min(needed[1], full[1])


@pytest.mark.parametrize("reduce", [2, 4, 8])
def test_reduced_decode_rounds_sizes_up_as_opencv_does(reduce: int) -> None:
    """A frame whose sides are no multiple of the reduction: both decoders and
    reduced_size agree on ceil(side / reduce)."""
    img = cv2.resize(_photo(), (323, 241))
    data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
    flag = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
            8: cv2.IMREAD_REDUCED_COLOR_8}[reduce]
    want = cv2.imdecode(np.frombuffer(data, np.uint8), flag)
    got = jpeg.decode(data, reduce=reduce)
    assert got is not None and got.shape == want.shape
    assert got.shape[1::-1] == jpeg.reduced_size((323, 241), reduce)
    assert int(np.abs(got.astype(int) - want).max()) <= 1


@pytest.mark.parametrize(("grey", "reduce"), [(False, 1), (True, 1), (False, 4), (True, 2)])
def test_opencv_fallback_decodes_like_simplejpeg(monkeypatch: pytest.MonkeyPatch, grey: bool,
                                                 reduce: int) -> None:
    """Without simplejpeg installed, OpenCV's IMREAD_REDUCED_* flags give the same sizes and
    pixels (within 1 level), so a plugin's max_size works either way."""
    img = cv2.resize(_photo(), (323, 241))
    data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
    turbo = jpeg.decode(data, grey=grey, reduce=reduce)
    monkeypatch.setattr(jpeg, "_sj", None)
    opencv = jpeg.decode(data, grey=grey, reduce=reduce)
    assert turbo is not None and opencv is not None and turbo.shape == opencv.shape
    assert int(np.abs(turbo.astype(int) - opencv).max()) <= 1
    assert jpeg.decode(b"\xff\xd8not-a-jpeg") is None
