"""A plugin for the `trapflow record` tests: a pool that takes its time to start, so a
pipeline stays in its start-up (supervisor up, runs/latest not yet moved) for a while."""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

from trapflow.plugin import Context, Extra, Pair, Worker


class SlowStart(Worker):
    """Sleeps `start_s` (default 10 s) in configure, then answers every pair at once."""

    needs_images = False

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        time.sleep(float(params.get("start_s", 10.0)))

    def process(self, pair: Pair) -> Extra:
        return Extra(name="slow_start", fields={"gap": pair.gap})
