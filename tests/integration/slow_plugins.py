"""Plugins for the tracking tests: the packaged crab detector made slower than the camera,
so that at policy `latest` it sees one pair in three or fewer, as on a small board."""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

from trapflow_workers.crab_detector import CrabDetector

from trapflow.plugin import Body, Context, Pair, Worker


class SlowDetector(Worker):
    """CrabDetector's detections, each pair taking `delay_s` (default 0.2 s) more."""

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        rest = dict(params)
        self.delay_s = float(rest.pop("delay_s", 0.2))
        self.inner = CrabDetector()
        self.inner.configure(rest, ctx)

    def activate(self) -> None:
        self.inner.activate()

    def process(self, pair: Pair) -> Body:
        time.sleep(self.delay_s)
        return self.inner.process(pair)

    def deactivate(self) -> None:
        self.inner.deactivate()

    def cleanup(self) -> None:
        self.inner.cleanup()
