"""Builders of plugin inputs (Pair, Context) for tests and benches: one place, no sockets."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.plugin import Context, Pair
from trapflow.wire.messages import StereoPair


def make_pair(
    left: np.ndarray,
    right: np.ndarray | None = None,
    seq: int = 0,
    gap: int = 0,
    header_size: tuple[int, int] | None = None,
) -> Pair:
    """A Pair as the worker process hands it to a plugin (header size = image size by default)."""
    right = left if right is None else right
    w, h = header_size or (left.shape[1], left.shape[0])
    header = StereoPair(
        seq=seq,
        t_wall_ns=0,
        t_mono_ns=0,
        t_left_ns=0,
        t_right_ns=0,
        skew_ns=0,
        encoding="raw",
        width=w,
        height=h,
    )
    return Pair(header=header, left=left, right=right, gap=gap)


def make_context(
    rig: StereoRig | None = None,
    pool: str = "test",
    run_dir: Path | None = None,
    extra: Mapping[str, Any] | None = None,
    tag_size_m: float | None = None,
) -> Context:
    """A Context for a plugin under test (default rig: 640x480, 70 degrees, 12 cm; the
    source's tag size: none known)."""
    return Context(
        pool=pool,
        worker=f"{pool}:0",
        run_dir=run_dir or Path("."),
        rig=rig or StereoRig.from_fov(640, 480, 70.0, 0.12),
        extra=extra or {},
        tag_size_m=tag_size_m,
    )
