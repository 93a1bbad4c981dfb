"""Builders for test data in one place: pair headers, encoded pairs, results."""

from __future__ import annotations

import time

import cv2
import numpy as np

from trapflow import messages


def pair_header(seq: int = 0, width: int = 64, height: int = 48,
                encoding: str = "jpeg") -> messages.StereoPair:
    now = time.monotonic_ns()
    return messages.StereoPair(
        seq=seq, t_wall_ns=time.time_ns(), t_mono_ns=now, t_left_ns=now, t_right_ns=now,
        skew_ns=0, encoding=encoding, width=width, height=height,  # type: ignore[arg-type]
    )


def image(width: int = 64, height: int = 48, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 255, size=(height, width, 3), dtype=np.uint8)


def jpeg(img: np.ndarray, quality: int = 90) -> bytes:
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return buf.tobytes()


def pair_frames(seq: int = 0, width: int = 64, height: int = 48,
                encoding: str = "jpeg") -> list[bytes]:
    """A valid [header, left, right] message."""
    h = pair_header(seq, width, height, encoding)
    left, right = image(width, height, seq), image(width, height, seq + 1)
    if encoding == "raw":
        return [messages.encode(h), left.tobytes(), right.tobytes()]
    return [messages.encode(h), jpeg(left), jpeg(right)]


def result(body: messages.Body, seq: int = 7, t_wall_ns: int = 1751892763120000000,
           pool: str = "mono") -> messages.Result:
    return messages.Result(seq=seq, t_wall_ns=t_wall_ns, t_mono_ns=1, pool=pool,
                           worker=f"{pool}:0:1", proc_ns=1000, body=body)
