"""The client side of `trapflow process`: a Dask cluster (local or by address), one task
per chunk, progress, resume, and per input results.jsonl, ledger.json and the summary.

Output, under --out: INPUT/results.jsonl (time order), INPUT/ledger.json (pairs read,
processed, failed with reasons, chunks, VO boundaries), INPUT/chunks/ (one finished
chunk = its lines + its ledger, written atomically), summary.txt and summary.json.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import logging
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec

from trapflow.batch.chunk import ChunkTask, atomic_write, chunk_paths, count_positions, run_chunk
from trapflow.batch.cleaner import start_cleaner
from trapflow.batch.plan import (
    WHOLE,
    Chunk,
    Input,
    Stitcher,
    fingerprint,
    plan_chunks,
)
from trapflow.config.schema import Config
from trapflow.errors import ConfigError
from trapflow.normalizer.result_json import dumps, parse_timestamp
from trapflow.tracking.rigpose import RigPoses
from trapflow.tracking.stage import track_pairs

log = logging.getLogger(__name__)

Echo = Callable[[str], None]
PROGRESS_INTERVAL_S = 0.5  # the progress line is redrawn at most this often


@dataclass(frozen=True)
class Options:
    """How `process` runs: pools, chunk sizes, retries and the cluster."""

    pools: tuple[str, ...]
    chunk: int = 64  # pairs per chunk of the stateless pools
    vo_chunk: int = WHOLE  # pairs per VO chunk; WHOLE keeps VO sequential
    vo_overlap: int = 4  # pairs a VO chunk starts early to re-initialise on
    retries: int = 2  # Dask retries of a failed chunk before it is reported
    local: int = 0  # LocalCluster workers (0: one per CPU core)
    scheduler: str | None = None  # an existing scheduler's address instead


@dataclass
class InputReport:
    """One input's outcome: its ledger (also written as INPUT/ledger.json)."""

    input: Input
    positions: int = 0
    chunks: list[dict[str, Any]] = field(default_factory=list)
    error: str = ""  # the input could not be counted or opened at all
    boundaries: list[dict[str, Any]] = field(default_factory=list)  # VO chunk hand-overs

    @property
    def failed_chunks(self) -> list[dict[str, Any]]:
        return [c for c in self.chunks if c["status"] == "failed"]


@dataclass
class Summary:
    """What `process` did, for the summary table and the exit status."""

    reports: list[InputReport]
    seconds: float
    dashboard: str
    resumed: int  # chunks found finished from an earlier run and skipped

    @property
    def failures(self) -> list[str]:
        out = [f"{r.input.name}: {r.error}" for r in self.reports if r.error]
        for r in self.reports:
            out += [f"{r.input.name} chunk {c['chunk']}: {c['error']}" for c in r.failed_chunks]
        return out


def _distributed() -> Any:
    """dask.distributed, imported on use (it ships no type hints; the rest of trapflow
    never needs it)."""
    return importlib.import_module("dask.distributed")


def worker_setup() -> None:
    """Run by every Dask worker as it joins: OpenCV on one thread. OpenCV's default is a
    thread per core in every process, so N workers on N cores ran N x N threads that took
    cores from one another (measured: the same pairs cost 6 % more CPU in one process with
    OpenCV's default threads than with one). onnxruntime already runs one intra-op and one
    inter-op thread per session (ModelParams.threads and inter_threads default to 1)."""
    import cv2

    cv2.setNumThreads(1)


LOOPBACK = "127.0.0.1"


def worker_environ() -> dict[str, Any]:
    """The environment Dask's nanny gives a local worker process, less
    MALLOC_TRIM_THRESHOLD_ (Dask sets 64 KiB so that long-lived workers hand freed memory
    back). With it glibc gives back and faults in again the pages of every image-sized
    buffer a pair allocates: 17.3 against 14.8 ms of worker CPU a pair at 640x360
    (mono, stereo, tags; the plain loop 13.2), 2 workers 1.47x then 1.72x the plain loop
    (benchmarks/process.py --pairs 480 --size 640x360 --chunk 16, same machine, quiet).
    A worker here holds a chunk's pairs at a time, so its memory stays bounded without it."""
    _distributed()  # registers the distributed.* defaults in dask's config
    config = importlib.import_module("dask").config
    env = dict(config.get("distributed.nanny.pre-spawn-environ", default={}) or {})
    env.pop("MALLOC_TRIM_THRESHOLD_", None)
    return env


# What a local cluster's processes do between tasks, less often: Dask's defaults suit a
# long-lived interactive cluster with its dashboard watched. Measured idle on 2 cores
# (one worker, 4 s): the worker 18.5 -> 4.0 ms of CPU a second, the client's process (the
# scheduler and the nannies) 22.0 -> 7.3; each key alone saved 1.5-5 ms/s. They slow only
# the dashboard's graphs, its profile page (empty) and how soon a memory limit is seen.
LOCAL_QUIET = {
    "distributed.worker.profile.enabled": False,  # stack samples every 10 ms
    "distributed.admin.tick.interval": "200ms",  # the event loops' liveness check (20 ms)
    "distributed.worker.memory.monitor-interval": "1s",  # RSS polled (100 ms)
    "distributed.admin.system-monitor.interval": "5s",  # CPU, memory, I/O polled (500 ms)
}


@contextmanager
def dask_client(opts: Options) -> Iterator[Any]:
    """A client of an existing scheduler, or of a LocalCluster of worker processes with one
    thread each (plugins and OpenCV are not shared across threads), closed on exit."""
    dd = _distributed()
    if opts.scheduler:
        try:
            client = dd.Client(opts.scheduler, timeout="10s")
        except OSError as exc:
            raise ConfigError(f"--scheduler {opts.scheduler}: cannot connect ({exc}); expected "
                              "the address of a running dask scheduler, e.g. "
                              "tcp://10.0.0.5:8786") from None
        with client:
            client.register_worker_callbacks(setup=worker_setup)
            yield client
        return
    n = opts.local or os.cpu_count() or 1
    # Dask's own logs stay quiet, errors included: a task that fails comes back to the
    # client with its error, which the input's ledger.json keeps and the summary names
    # (Dask logged each failure with its traceback once per retry: 23 lines for one error).
    # Scheduler and dashboard on loopback: ":0" served the dashboard (the run's tasks, logs
    # and a profiler) to the whole network (issue 26 item 10).
    config = importlib.import_module("dask").config
    start_cleaner()  # before any semaphore of the cluster exists (batch/cleaner.py)
    with config.set({"distributed.nanny.pre-spawn-environ": worker_environ(), **LOCAL_QUIET}), \
            dd.LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host=LOOPBACK,
                            dashboard_address=f"{LOOPBACK}:0",
                            silence_logs=logging.CRITICAL) as cluster, \
            dd.Client(cluster) as client:
        client.register_worker_callbacks(setup=worker_setup)
        yield client


def ordered_pools(cfg: Config, pools: tuple[str, ...]) -> frozenset[str]:
    """The pools of the run that keep pair order (PoolConfig.ordered, as live)."""
    return frozenset(p for p in pools if cfg.pools[p].ordered)


def _plan_key(cfg_data: dict[str, Any], inp: Input, opts: Options,
              ordered: frozenset[str]) -> str:
    return fingerprint({"config": cfg_data, "input": [inp.kind, inp.uri],
                        "pools": opts.pools, "chunk": opts.chunk, "vo_chunk": opts.vo_chunk,
                        "vo_overlap": opts.vo_overlap, "ordered": sorted(ordered)})


def _finished(task: ChunkTask) -> dict[str, Any] | None:
    """The ledger of a chunk an earlier run finished with the same plan, else None."""
    lines, ledger = chunk_paths(task.out, task.chunk)
    try:
        done: dict[str, Any] = json.loads(ledger.read_bytes())
    except (OSError, ValueError):
        return None
    return done if done.get("fingerprint") == task.fingerprint and lines.is_file() else None


def progress_line(done_chunks: int, chunks: int, done_pairs: int, pairs: int,
                  elapsed_s: float, workers: int) -> str:
    """The progress line: chunks, pairs, rate and ETA. While the first wave is out (fewer
    chunks done than workers), the other workers' chunks are about as far along as the
    finished ones, so the rate counts them: an ETA from the first chunk, not N times too
    long. Before any chunk is done, rate and ETA are '-'."""
    width = 24
    filled = int(width * done_chunks / max(chunks, 1))
    bar = "#" * filled + "." * (width - filled)
    wave = min(max(workers, 1), max(chunks, 1))
    if done_pairs and elapsed_s > 0:
        rate = done_pairs / elapsed_s * max(1.0, wave / max(done_chunks, 1))
        speed, eta = f"{rate:.1f} pairs/s", f"{(pairs - done_pairs) / rate:.0f}s"
    else:
        speed, eta = "- pairs/s", "-"
    return (f"[{bar}] chunks {done_chunks}/{chunks}  pairs {done_pairs}/{pairs}  "
            f"{speed}  ETA {eta}")


class Progress:
    """One line over chunks and pairs with rate and ETA: redrawn in place on a terminal,
    else written at most every LOG_INTERVAL_S (and once at the start and at the end) for
    a log file."""

    LOG_INTERVAL_S = 5.0

    def __init__(self, chunks: int, pairs: int, stream: IO[str], workers: int = 1) -> None:
        self.chunks, self.pairs, self.workers = chunks, pairs, workers
        self.done_chunks = self.done_pairs = 0
        self.t0 = time.monotonic()
        self.next_draw = 0.0
        self.stream = stream
        self.tty = stream.isatty()
        if chunks:
            self._draw(self.t0, last=False)

    def add(self, pairs: int) -> None:
        self.done_chunks += 1
        self.done_pairs += pairs
        now = time.monotonic()
        last = self.done_chunks >= self.chunks
        # The first chunk's line is drawn at once: it carries the first rate and ETA.
        if now < self.next_draw and not last and self.done_chunks > 1:
            return
        self._draw(now, last)

    def _draw(self, now: float, last: bool) -> None:
        self.next_draw = now + (PROGRESS_INTERVAL_S if self.tty else self.LOG_INTERVAL_S)
        if self.tty:
            self.stream.write("\r" + self.line(now) + ("\n" if last else ""))
        else:
            self.stream.write(self.line(now) + "\n")
        self.stream.flush()

    def line(self, now: float) -> str:
        return progress_line(self.done_chunks, self.chunks, self.done_pairs, self.pairs,
                             now - self.t0, self.workers)


def process(cfg: Config, inputs: list[Input], out: Path, opts: Options, echo: Echo,
            echo_err: Echo | None = None, progress_stream: IO[str] | None = None) -> Summary:
    """Run every input's chunks on the cluster; write results, ledgers and the summary.
    `echo` gets a line per input at the end, `echo_err` notes, `progress_stream` (default
    stderr) the progress line."""
    # Long on purpose: the client's sequence read top-down (plan, resume, cluster, submit,
    # progress, per-input files, summary), as boot() reads for the live pipeline.
    err = echo_err or echo
    unknown = [p for p in opts.pools if p not in cfg.pools]
    if unknown:
        raise ConfigError(f"--workers: pool(s) {', '.join(unknown)} not in the config; "
                          f"expected some of {', '.join(cfg.pools)}")
    cfg_data: dict[str, Any] = msgspec.to_builtins(cfg)
    ordered = ordered_pools(cfg, opts.pools)
    t0 = time.monotonic()
    out.mkdir(parents=True, exist_ok=True)
    with dask_client(opts) as client:
        info = client.scheduler_info()
        dashboard = str(client.dashboard_link or "")
        # The scheduler answers on that address either way; its pages need bokeh.
        note = "" if importlib.util.find_spec("bokeh") else (
            " (its pages need bokeh installed where the scheduler runs)")
        err(f"dask: {len(info.get('workers', {}))} workers at {client.scheduler.address}; "
            f"dashboard {dashboard or 'not served'}{note}")
        counts = {inp.name: client.submit(count_positions, cfg_data, inp, retries=opts.retries,
                                          pure=False) for inp in inputs}
        reports = {inp.name: InputReport(inp) for inp in inputs}
        futures: dict[Any, ChunkTask] = {}
        resumed = 0
        total_pairs = 0
        for inp in inputs:
            report = reports[inp.name]
            try:
                report.positions = int(counts[inp.name].result())
            except Exception as exc:  # noqa: BLE001 - an unreadable input is reported, others go on
                report.error = f"cannot read the input: {exc}"
                continue
            key = _plan_key(cfg_data, inp, opts, ordered)
            for chunk in plan_chunks(inp.name, report.positions, opts.pools, opts.chunk,
                                     opts.vo_chunk, opts.vo_overlap, ordered):
                task = ChunkTask(cfg_data, inp, chunk, str(out / inp.name), key)
                done = _finished(task)
                if done is not None:
                    resumed += 1
                    report.chunks.append({**done, "status": "resumed"})
                    continue
                total_pairs += chunk.end - chunk.first
                fut = client.submit(run_chunk, task, retries=opts.retries, pure=False,
                                    key=f"trapflow-chunk-{inp.name}-{chunk.key}-{time.time_ns()}")
                futures[fut] = task
        if resumed:
            err(f"resume: {resumed} finished chunks in {out} skipped")
        progress = Progress(len(futures), total_pairs, progress_stream or sys.stderr,
                            workers=len(info.get("workers", {})))
        for fut in _distributed().as_completed(list(futures)):
            task = futures[fut]
            chunk = task.chunk
            entry: dict[str, Any]
            if fut.status == "finished":
                entry = {**fut.result(), "status": "done"}
            else:
                why = fut.exception()
                entry = {"chunk": chunk.key, "start": chunk.start, "first": chunk.first,
                         "end": chunk.end, "pools": list(chunk.pools),
                         "ordered": chunk.ordered, "status": "failed",
                         "error": f"{type(why).__name__}: {why}"[:500]}
                err(f"{task.input.name}: chunk {chunk.key} failed after {opts.retries} "
                    f"retries: {entry['error']}")
            reports[task.input.name].chunks.append(entry)
            progress.add(chunk.end - chunk.first)
    for report in reports.values():
        _write_input(out / report.input.name, report, opts, cfg)
    summary = Summary(list(reports.values()), time.monotonic() - t0, dashboard, resumed)
    text = summary_table(summary)
    atomic_write(out / "summary.txt", text.encode())
    atomic_write(out / "summary.json", json.dumps(
        [ledger_of(r, opts) for r in summary.reports], indent=1).encode())
    for report in summary.reports:
        echo(input_line(report, opts))
    return summary


def _sum(chunks: list[dict[str, Any]], what: str, pools: tuple[str, ...]) -> dict[str, int]:
    out = dict.fromkeys(pools, 0)
    for c in chunks:
        for pool, n in c.get(what, {}).items():
            out[pool] = out.get(pool, 0) + n
    return out


def ledger_of(report: InputReport, opts: Options) -> dict[str, Any]:
    """The input's ledger: pairs read, processed and failed per pool with reasons, chunks."""
    chunks = sorted(report.chunks, key=lambda c: (c["pools"], c["first"]))
    stateless = [c for c in chunks if not c.get("ordered")]
    grid = stateless or chunks  # read positions counted once, on one chunk grid
    reasons: dict[str, list[str]] = {}
    skipped: dict[str, int] = {}
    for c in chunks:
        for pool, why in c.get("reasons", {}).items():
            reasons.setdefault(pool, []).extend(r for r in why if r not in reasons.get(pool, []))
    for c in grid:
        for kind, n in c.get("skipped", {}).items():
            skipped[kind] = skipped.get(kind, 0) + n
    return {
        "input": report.input.name, "kind": report.input.kind, "uri": report.input.uri,
        "positions": report.positions, "error": report.error,
        "read": sum(c.get("read", 0) for c in grid if c["status"] != "failed"),
        "skipped": skipped,
        "processed": _sum(chunks, "processed", opts.pools),
        "failed": _sum(chunks, "failed", opts.pools),
        "reasons": reasons,
        "chunks": [{k: c.get(k) for k in ("chunk", "pools", "first", "end", "status",
                                          "seconds", "host", "error") if k in c}
                   for c in chunks],
        "vo_boundaries": report.boundaries,
    }


def _write_input(folder: Path, report: InputReport, opts: Options, cfg: Config) -> None:
    """INPUT/results.jsonl in time order (VO poses chained across chunks, detections
    tracked over the whole input), its tracks.jsonl and counts.jsonl, and ledger.json."""
    decimals = cfg.normalizer.decimals
    lines: list[tuple[int, int, dict[str, Any]]] = []
    stitchers: dict[str, Stitcher] = {}
    boundaries: list[dict[str, Any]] = []
    order = {pool: i for i, pool in enumerate(opts.pools)}
    for c in sorted(report.chunks, key=lambda c: (c["pools"], c["first"])):
        if c["status"] == "failed":
            continue
        chunk = Chunk(report.input.name, tuple(c["pools"]), c["start"], c["end"], c["first"],
                      bool(c.get("ordered")))
        path, _ledger = chunk_paths(str(folder), chunk)
        raw = [json.loads(x) for x in path.read_bytes().splitlines() if x.strip()]
        rank = min(order.get(p, 0) for p in chunk.pools)
        if chunk.ordered:  # VO's poses chained; the overlap's other results are the predecessor's
            st = stitchers.setdefault(chunk.pools[0], Stitcher(decimals))
            vo = [x for x in raw if "stereo_vo" in x]
            raw = [x for x in raw if "stereo_vo" not in x
                   and next(iter(x.values()))["seq"] >= chunk.first] + st.add(chunk, vo)
        lines += [(next(iter(x.values()))["seq"], rank, x) for x in raw]
    for st in stitchers.values():
        boundaries += [b.as_dict() for b in st.boundaries]
    report.boundaries = boundaries
    lines.sort(key=lambda t: (t[0], t[1]))
    folder.mkdir(parents=True, exist_ok=True)
    if cfg.observe.enabled:  # tracks across chunks: the whole input, in capture order
        objs = [x for _s, _r, x in lines]
        obs = track_pairs(_detections_by_pair(objs), cfg.observe, rig_poses(objs))
        for name, objs in ((cfg.observe.tracks_file, obs.tracks),
                           (cfg.observe.counts_file, obs.counts)):
            atomic_write(folder / name, b"".join(dumps(o) + b"\n" for o in objs))
    atomic_write(folder / "results.jsonl", b"".join(dumps(x) + b"\n" for _s, _r, x in lines))
    atomic_write(folder / "ledger.json", json.dumps(ledger_of(report, opts), indent=1).encode())


def _detections_by_pair(objs: list[dict[str, Any]]) -> list[tuple[int, list[dict[str, Any]]]]:
    """(capture time ns, the pair's mono_ir items) for each pair, in the lines' order."""
    pairs: dict[int, list[dict[str, Any]]] = {}
    for obj in objs:
        if (item := obj.get("mono_ir")) is not None:
            pairs.setdefault(item["seq"], []).append(item)
    return [(parse_timestamp(items[0]["timestamp"]), items) for items in pairs.values()]


def rig_poses(objs: list[dict[str, Any]]) -> RigPoses:
    """VO's poses (chained across chunks) by capture time, for the tracks' speeds over the
    ground."""
    poses = RigPoses(keep_s=float("inf"))  # the whole input is at hand: nothing to forget
    for obj in objs:
        vo = obj.get("stereo_vo")
        if vo is None or len(vo.get("pose", ())) != 3:
            continue
        rows = [float(v) for row in vo["pose"] for v in row]
        poses.add(parse_timestamp(vo["timestamp"]) / 1e9, tuple(rows), bool(vo.get("ok")),
                  bool(vo.get("reinit", False)))
    return poses


def input_line(report: InputReport, opts: Options) -> str:
    """One line per input at the end."""
    led = ledger_of(report, opts)
    if report.error:
        return f"{report.input.name}: FAILED: {report.error}"
    done = sum(1 for c in led["chunks"] if c["status"] != "failed")
    parts = [f"{p} {led['processed'][p]} ok/{led['failed'][p]} failed" for p in opts.pools]
    drift = [b for b in led["vo_boundaries"] if b["drift_translation_m"] is not None]
    vo = ""
    if led["vo_boundaries"]:
        worst = max((b["drift_translation_m"] for b in drift), default=None)
        vo = (f"; vo: {len(led['vo_boundaries'])} chunk boundaries"
              + (f", worst drift {worst:.3f} m" if worst is not None else ""))
    return (f"{report.input.name}: {led['read']}/{report.positions} pairs read, "
            f"{', '.join(parts)}; chunks {done}/{len(led['chunks'])} done{vo}")


def summary_table(summary: Summary) -> str:
    """A plain-text table: one row per input, then the totals and the time taken."""
    head = f"{'input':<32} {'pairs':>7} {'read':>7} {'processed':>10} {'failed':>7} {'chunks':>9}"
    rows = [head, "-" * len(head)]
    for r in summary.reports:
        chunks = r.chunks
        processed = sum(sum(c.get("processed", {}).values()) for c in chunks)
        failed = sum(sum(c.get("failed", {}).values()) for c in chunks)
        stateless = [c for c in chunks if not c.get("ordered")] or chunks
        read = sum(c.get("read", 0) for c in stateless)
        ok = sum(1 for c in chunks if c["status"] != "failed")
        rows.append(f"{r.input.name[:32]:<32} {r.positions:>7} {read:>7} {processed:>10} "
                    f"{failed:>7} {f'{ok}/{len(chunks)}':>9}" + ("  ERROR" if r.error else ""))
    rows.append(f"{summary.seconds:.1f} s; {summary.resumed} chunks resumed; "
                f"{len(summary.failures)} failures")
    return "\n".join(rows) + "\n"
