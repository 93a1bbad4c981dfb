"""The plugin author's kit: make a Pair and a Context as a worker hands them to a plugin, and
run a plugin on pairs to get the lines the normalizer writes, with no process or socket.

    from trapflow.testing import make_context, make_pair, run_plugin
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from trapflow import registry
from trapflow.calibration.camera import StereoRig
from trapflow.normalizer.result_json import normalize
from trapflow.plugin import Context, Pair, Worker, configure_plugin
from trapflow.pools.pair_path import process_pair
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


def run_plugin(plugin: type[Worker] | str, pairs: Iterable[tuple[np.ndarray, np.ndarray]],
               params: Mapping[str, Any] | None = None, ctx: Context | None = None,
               pool: str = "test") -> list[dict[str, Any]]:
    """Run a plugin on raw BGR pairs as a worker would (configure, activate, the one per-pair
    path that decodes, runs and builds the result) and return the lines the normalizer would
    write to results.jsonl for them, in order. `plugin`: a Worker class, or a name or
    `module:Class` path as a pool's `plugin:` key takes it.

        lines = run_plugin(MyDetector, [(left, right)], params={"conf_threshold": 0.5})
        assert lines[0]["my_detector"]["label"] == "crab"
    """
    cls = registry.resolve(plugin) if isinstance(plugin, str) else plugin
    worker = cls()
    context = ctx or make_context(pool=pool)
    configure_plugin(worker, params or {}, context)
    worker.activate()
    lines: list[dict[str, Any]] = []
    try:
        for seq, (left, right) in enumerate(pairs):
            header = make_pair(left, right, seq=seq).header
            done = process_pair(worker, header, np.ascontiguousarray(left),
                                np.ascontiguousarray(right), pool=context.pool,
                                worker=context.worker, calib=context.rig.id)
            lines.extend(normalize(done.result))
    finally:
        worker.deactivate()
    return lines
