"""Plugins for the recycling tests: one that grows its process's memory with every pair,
as a leaking algorithm would, and reports its resident size."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import psutil

from trapflow.plugin import Context, Pair, Worker
from trapflow.wire.messages import Extra


class Grow(Worker):
    """Allocates and keeps `mb` MiB (default 20) per pair, every page touched, so the
    worker's RSS grows by that much each time."""

    needs_images = False

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        self.mb = int(params.get("mb", 20))
        self.kept: list[np.ndarray] = []
        self.proc = psutil.Process()

    def process(self, pair: Pair) -> Extra:
        self.kept.append(np.ones(self.mb << 20, dtype=np.uint8))  # written: resident
        rss_mb = self.proc.memory_info().rss >> 20
        return Extra(name="grow", fields={"pid": self.proc.pid, "rss_mb": rss_mb,
                                          "kept_mb": self.mb * len(self.kept)})
