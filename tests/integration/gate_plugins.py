"""Detectors for the gate's pipeline tests: one that sees the same still animal in every
pair it is given (a track that lives as long as it is fed), and one that sees nothing."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from trapflow.plugin import Context, Pair, Worker
from trapflow.wire.messages import Detection, MonoIR


class StillAnimal(Worker):
    """One crab at a fixed box in every pair, at confidence 0.9."""

    needs_images = False

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        self.box = (100.0, 100.0, 180.0, 160.0)

    def process(self, pair: Pair) -> MonoIR:
        return MonoIR(detections=[Detection(label="crab", confidence=0.9, box=self.box)])


class NoAnimal(Worker):
    """Never a detection: no track ever holds the gate open."""

    needs_images = False

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        pass

    def process(self, pair: Pair) -> MonoIR:
        return MonoIR()
