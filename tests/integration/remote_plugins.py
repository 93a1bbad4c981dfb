"""Plugins for the remote worker tests: the packaged crab detector, its result tagged
with the pool and worker that computed it (results.jsonl does not say which pool made a
mono_ir line), so a local and a remote pool can be compared pair for pair."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from trapflow_workers.crab_detector import CrabDetector

from trapflow.plugin import Context, Pair, Worker
from trapflow.wire.messages import Extra, MonoIR


class PooledDetector(Worker):
    """CrabDetector's detections as [label, confidence, x1, y1, x2, y2], with pool and worker."""

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        self.pool, self.worker = ctx.pool, ctx.worker
        self.inner = CrabDetector()
        self.inner.configure(params, ctx)

    def activate(self) -> None:
        self.inner.activate()

    def process(self, pair: Pair) -> Extra:
        body = self.inner.process(pair)
        assert isinstance(body, MonoIR)
        dets = [[d.label, d.confidence, *d.box] for d in body.detections]
        return Extra(name="pooled", fields={"pool": self.pool, "worker": self.worker,
                                            "detections": dets})
