"""The task a Dask worker runs: one chunk of one input, read where the task runs.

The task gets paths and a range, never frames. It opens the input as `trapflow start`
would (same source, rig and plugins), steps to its first read position, and puts every
pair through what the live path does to it: the capture's encoding (JPEG at the
configured quality, or raw), the worker's decoding, the plugin, the rig stamp and the
normalizer. Its lines and its ledger are written atomically under OUT/INPUT/chunks/;
the ledger, written last, marks the chunk finished for a resumed run.
"""

from __future__ import annotations

import atexit
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from trapflow import registry
from trapflow.batch.plan import Chunk, Input, fingerprint
from trapflow.calibration.camera import StereoRig
from trapflow.config import schema as configmod
from trapflow.config.schema import Config
from trapflow.errors import WorkerError
from trapflow.normalizer.result_json import dumps, normalize
from trapflow.plugin import Context, Pair, Worker, configure_plugin
from trapflow.pools.pair_path import Need, process_pair
from trapflow.sources.base import SkipPair, Source
from trapflow.sources.factory import open_source
from trapflow.sources.rig import describe, mismatch, run_calibration
from trapflow.wire import jpeg, messages

log = logging.getLogger(__name__)

REASONS_KEPT = 5  # distinct failure reasons a ledger keeps per pool (the counts keep all)


@dataclass(frozen=True)
class ChunkTask:
    """Everything a task needs, all small and picklable: config as plain data, paths."""

    config: dict[str, Any]
    input: Input
    chunk: Chunk
    out: str  # the input's output folder
    fingerprint: str


def input_config(config: dict[str, Any], inp: Input) -> Config:
    """The run's config with this input as a finite source read as fast as it can be."""
    cfg = configmod.from_data(config, "config")
    options = dict(cfg.source.options)
    if inp.kind == "replay":
        options["rate"] = 0  # no original timing to keep: as fast as the plugins go
    return configmod.with_source(cfg, kind=inp.kind, uri=inp.uri, loop=False, options=options)


def open_input(cfg: Config) -> Source:
    """The input's source, opened, with the run's rig (trapflow.sources.rig decides it)."""
    resolved = describe(cfg)
    source = open_source(cfg.source, resolved.rig, run_calibration(cfg))
    source.open()
    return source


def seek(source: Source, position: int) -> None:
    """Step past the first `position` read positions without decoding where the source
    allows it (image folders, recordings), else by reading them."""
    from trapflow.sources.images import ImagesSource
    from trapflow.sources.replay import ReplaySource

    if position <= 0:
        return
    if isinstance(source, ImagesSource):
        source._i = source._index = min(position, len(source.pairs))
        return
    if isinstance(source, ReplaySource):
        for _ in range(position):
            if source._next_pair() is None:
                return
            source.pairs_read += 1
        return
    for _ in range(position):
        try:
            if source.read() is None:
                return
        except SkipPair:
            continue


def count_positions(config: dict[str, Any], inp: Input) -> int:
    """How many read positions the input has (one pass; cheap for folders and recordings)."""
    from trapflow.sources.images import ImagesSource
    from trapflow.sources.replay import ReplaySource

    cfg = input_config(config, inp)
    if inp.kind == "replay":
        return ReplaySource(cfg.source, describe(cfg).rig).count_pairs()
    source = open_input(cfg)
    try:
        if isinstance(source, ImagesSource):
            return len(source.pairs)
        n = 0
        while True:
            try:
                if source.read() is None:
                    return n
            except SkipPair:
                pass
            n += 1
    finally:
        source.close()


class _Ledger:
    def __init__(self, pools: tuple[str, ...]) -> None:
        self.read = 0
        self.skipped: dict[str, int] = {}
        self.processed = dict.fromkeys(pools, 0)
        self.failed = dict.fromkeys(pools, 0)
        self.reasons: dict[str, list[str]] = {p: [] for p in pools}

    def fail(self, pool: str, reason: str) -> None:
        self.failed[pool] += 1
        kept = self.reasons[pool]
        if reason not in kept and len(kept) < REASONS_KEPT:
            kept.append(reason)

    def as_dict(self) -> dict[str, Any]:
        return {"read": self.read, "skipped": self.skipped, "processed": self.processed,
                "failed": self.failed, "reasons": self.reasons}


# Configured plugins of this Dask worker process, kept from chunk to chunk: a model loads
# once per worker, not once per chunk (measured: ~150 ms of every task at 320x240). Only
# built-in plugins of pools that are not ordered, whose results never depend on earlier
# pairs; an ordered pool's plugin, or a third-party one, may keep state, so it starts
# fresh in every chunk.
_KEPT: dict[tuple[str, str], tuple[Worker, str]] = {}


def _reusable(cfg: Config, pool: str) -> bool:
    return not cfg.pools[pool].ordered and cfg.plugin_of(pool) in registry.BUILTIN


def _start_plugins(cfg: Config, task: ChunkTask, rig: StereoRig,
                   plugins: dict[str, tuple[Worker, str]]) -> None:
    """Configure (or take the kept) plugin of every pool of the chunk and activate it,
    into `plugins` as it goes, so that a failure stops those already started."""
    for pool in task.chunk.pools:
        pcfg = cfg.pools[pool]
        key = (pool, fingerprint([msgspec.to_builtins(pcfg), cfg.plugin_of(pool), rig.id]))
        kept = _KEPT.get(key) if _reusable(cfg, pool) else None
        if kept is None:
            plugin = registry.resolve(cfg.plugin_of(pool))()
            ctx = Context(pool=pool, worker=f"batch:{pool}:{os.getpid()}",
                          run_dir=Path(task.out), rig=rig, debug=pcfg.debug, save=False,
                          time=pcfg.time, extra={"input": task.input.name,
                                                 "chunk": (task.chunk.first, task.chunk.end)})
            configure_plugin(plugin, pcfg.params, ctx)
            kept = (plugin, (plugin.rig or rig).id)  # a plugin's own calibration wins
            if _reusable(cfg, pool):
                if not _KEPT:
                    atexit.register(_release_kept)
                _KEPT[key] = kept
        kept[0].activate()
        plugins[pool] = kept


def _stop_plugins(plugins: dict[str, tuple[Worker, str]]) -> None:
    """Deactivate every plugin of the chunk; release those not kept for the next chunk."""
    kept = {id(p) for p, _calib in _KEPT.values()}
    for plugin, _calib in plugins.values():
        plugin.deactivate()
        if id(plugin) not in kept:
            plugin.cleanup()
            plugin.shutdown()


def _release_kept() -> None:
    for plugin, _calib in _KEPT.values():
        plugin.cleanup()
        plugin.shutdown()
    _KEPT.clear()


def _encode(img: np.ndarray, cfg: Config) -> np.ndarray:
    """As the capture does: raw bytes or one JPEG at the configured quality."""
    try:
        return jpeg.wire_side(img, cfg.source.encoding, cfg.source.jpeg_quality)
    except ValueError as exc:
        raise WorkerError(str(exc)) from None


def _time_base(uri: str) -> int:
    """Wall-clock label of position 0 for an input without capture times of its own (files:
    a recording gives each pair's): its modification time, the same for every chunk."""
    path = Path(uri.split(",")[0])
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return 0


def atomic_write(path: Path, data: bytes) -> None:
    """Write a file whole or not at all (a temporary beside it, fsynced, then renamed)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def chunk_paths(out: str, chunk: Chunk) -> tuple[Path, Path]:
    """(lines, ledger) files of a chunk; the ledger exists only once the chunk is finished."""
    folder = Path(out) / "chunks"
    return folder / f"{chunk.key}.jsonl", folder / f"{chunk.key}.json"


def run_chunk(task: ChunkTask) -> dict[str, Any]:
    """Process one chunk and write its files; returns its ledger (also written)."""
    # Long on purpose: one chunk's life in the order a resume relies on (open, skip what the
    # chunk file already holds, per-pair loop, ledger, atomic write); split, that order would
    # be spread over functions that each hold half of the state.
    t0 = time.monotonic()
    cfg = input_config(task.config, task.input)
    chunk = task.chunk
    source = open_input(cfg)
    rig = source.rig
    period_ns = int(1e9 / cfg.source.rate_hz)
    base_ns = _time_base(task.input.uri)
    ledger = _Ledger(chunk.pools)
    out: list[bytes] = []
    plugins: dict[str, tuple[Worker, str]] = {}
    try:
        _start_plugins(cfg, task, rig, plugins)
        seek(source, chunk.start)
        for pos in range(chunk.start, chunk.end):
            own = pos >= chunk.first  # a VO chunk's overlap warms it up; its predecessor counts
            try:
                frames = source.read()
            except SkipPair as exc:
                if own:
                    ledger.skipped[exc.kind] = ledger.skipped.get(exc.kind, 0) + 1
                continue
            if frames is None:
                break
            ledger.read += own
            h, w = frames.left.shape[:2]
            if frames.right.shape != frames.left.shape or (w, h) != rig.size:
                why = ("size" if frames.right.shape != frames.left.shape else "geometry")
                if own:
                    ledger.skipped[why] = ledger.skipped.get(why, 0) + 1
                if own and why == "geometry":
                    log.warning("pair %d skipped: %s", pos, mismatch(
                        (w, h), task.input.name, rig, f"calib {rig.id}"))
                continue
            left_buf, right_buf = _encode(frames.left, cfg), _encode(frames.right, cfg)
            header = messages.StereoPair(
                seq=pos, t_mono_ns=frames.t_left_ns,
                t_wall_ns=(base_ns + pos * period_ns if frames.t_wall_ns is None
                           else frames.t_wall_ns),
                t_left_ns=frames.t_left_ns, t_right_ns=frames.t_right_ns,
                skew_ns=frames.right_minus_left_ns(), encoding=cfg.source.encoding,
                width=w, height=h, source=cfg.source.kind)
            # Decoded as a worker decodes its job (colour, DCT reduction), once per need.
            decoded: dict[Need, Pair] = {}
            for pool, (plugin, calib) in plugins.items():
                try:
                    got = process_pair(plugin, header, left_buf, right_buf, pool=pool,
                                       worker=f"batch:{pool}:{os.getpid()}", calib=calib,
                                        decoded=decoded)
                except Exception as exc:  # noqa: BLE001 - one bad pair fails, the chunk goes on
                    reason = str(exc) if isinstance(exc, WorkerError) else (
                        f"{type(exc).__name__}: {exc}")
                    if own:
                        ledger.fail(pool, reason[:300])
                    continue
                ledger.processed[pool] += own
                out += [dumps(obj) for obj in normalize(got.result, cfg.normalizer.decimals)]
    finally:
        _stop_plugins(plugins)
        source.close()
    lines_path, ledger_path = chunk_paths(task.out, chunk)
    lines_path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(lines_path, b"".join(line + b"\n" for line in out))
    done = {"chunk": chunk.key, "start": chunk.start, "first": chunk.first, "end": chunk.end,
            "pools": list(chunk.pools), "ordered": chunk.ordered,
            "fingerprint": task.fingerprint,
            "seconds": round(time.monotonic() - t0, 3), "host": os.uname().nodename,
            **ledger.as_dict()}
    atomic_write(ledger_path, json.dumps(done).encode())
    return done
