"""Plugins for the `trapflow process` tests, loaded by import path on Dask workers."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from trapflow.errors import WorkerError
from trapflow.plugin import Context, Pair, Worker
from trapflow.wire.messages import Extra


class FailChunk(Worker):
    """Fails the chunk whose results start at `first` when it starts (configure), every
    time, or only the first time when `marker` names a file (it is created then).
    Each start of that chunk adds a line to `tally`: how often Dask ran it."""

    needs_images = False

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        start = ctx.extra["chunk"][0]
        if start != int(params["first"]):
            return
        with open(params["tally"], "a", encoding="utf-8") as fh:
            fh.write(f"{start}\n")
        marker = params.get("marker")
        if marker and Path(marker).exists():
            return
        if marker:
            Path(marker).touch()
        raise WorkerError(f"chunk starting at {start} fails on purpose (test)")

    def process(self, pair: Pair) -> Extra:
        return Extra(name="fail_chunk", fields={"bytes": int(pair.left.size)})
