"""What a run reports while it runs and when it ends: the status reply, the status line,
ledger.json and the totals. Owns no socket; reads results.jsonl (the ledger's truth).
The counting is trapflow.supervisor.ledger's; what changes during a run comes to the report
as a Snapshot the supervisor builds on demand, so the report knows nothing of its class.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import msgspec

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import Config, EnergyConfig
from trapflow.power.energy import BOARDS, estimate
from trapflow.runtime.files import SpaceReserve, is_disk_full, write_atomically
from trapflow.supervisor import ledger as run_ledger
from trapflow.supervisor import run_meta, status_line
from trapflow.supervisor import summary as run_summary
from trapflow.supervisor.ledger import RunLedger
from trapflow.supervisor.state import SupervisorState
from trapflow.wire import messages
from trapflow.wire.frame_ring import FrameRing

# results.jsonl is read incrementally for the ledger, at most this much per status tick.
RESULTS_READ_BYTES = 4 << 20
RESULTS_READS_AT_END = 10_000
# counts.jsonl's last line is looked for in this much of its end (a line is a few hundred
# bytes per label).
COUNTS_TAIL_BYTES = 64 << 10
# Space put aside at the start for ledger.json and run.json, freed to write them at the end:
# a run whose disk filled up still leaves its ledger (a few kB; a long run's timeline more).
LEDGER_RESERVE_BYTES = 1 << 20
LEDGER_RESERVE = ".ledger.reserve"
# The normalizer's counters of lines a full disk kept out of its files, by file.
DISK_FULL_PREFIX = "disk_full:"


@dataclass(frozen=True)
class NodeView:
    """One supervised process as a report shows it."""

    name: str
    pid: int | None
    pool: str  # "" for a node that is not a pool's worker
    counters: dict[str, int]


@dataclass(frozen=True)
class Snapshot:
    """What of a running supervisor changes under a report: its nodes, totals and rig."""

    nodes: list[NodeView]
    stats: messages.Stats | None
    planned_stop: bool
    rig: StereoRig | None
    rig_origin: str
    source_where: str
    ring: FrameRing | None
    cpu_s: dict[str, float]  # CPU seconds per role so far (trapflow.power.cpu)


def energy_section(cfg: EnergyConfig, cpu_s: dict[str, float], wall_s: float,
                   gate_s: tuple[int, int] | None = None) -> dict[str, Any]:
    """ledger.json's `energy`: the board's power model over this run's CPU per role, and
    with a motion gate the seconds it was open (`active_s`) and idle (`idle_s`)."""
    est = estimate(BOARDS[cfg.board], cpu_s, max(wall_s, 1e-3), cameras=cfg.cameras)
    out: dict[str, Any] = {
        "board": cfg.board, "wall_s": round(wall_s, 1), "cpu_s": cpu_s,
        "cpu_s_per_hour": {role: round(v, 1) for role, v in est.cpu_s_per_hour.items()},
        "busy_cores": round(est.busy_cores, 3), "watts": round(est.watts, 2),
        "wh_per_day": round(est.wh_per_day, 1)}
    if cfg.battery_wh > 0:
        out["days_on_battery"] = round(est.days(cfg.battery_wh, cfg.usable), 1)
    if gate_s is not None:
        out["active_s"], out["idle_s"] = gate_s
    return out


def energy_text(energy: dict[str, Any]) -> str:
    """One line for the end of a run and `trapflow status`."""
    days = (f", {energy['days_on_battery']} days on the battery"
            if "days_on_battery" in energy else "")
    gate = ""
    if "active_s" in energy:
        active, idle = energy["active_s"], energy["idle_s"]
        share = f" ({100 * active / (active + idle):.0f} %)" if active + idle else ""
        gate = f"; motion gate active {active} s{share}, idle {idle} s"
    return (f"energy ({energy['board']} model): {energy['busy_cores']} cores busy, "
            f"{energy['watts']} W, {energy['wh_per_day']} Wh/day{days}{gate}\n")


def _full_stats(stats: messages.Stats) -> dict[str, Any]:
    """Stats as plain data with every field, zeros included (the wire form omits them)."""
    out = msgspec.structs.asdict(stats)
    out["pools"] = {n: msgspec.structs.asdict(p) for n, p in stats.pools.items()}
    if stats.image is not None:
        out["image"] = msgspec.structs.asdict(stats.image)
    return out


def latest_counts(path: Path) -> dict[str, Any] | None:
    """The last closed interval in counts.jsonl (its `counts` object), or None while none has
    closed; a line still being written is passed over for the one before it."""
    try:
        with open(path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - COUNTS_TAIL_BYTES))
            tail = f.read()
    except FileNotFoundError:
        return None
    for line in reversed(tail.splitlines()):
        try:
            obj = json.loads(line)
        except ValueError:
            continue
        if isinstance(obj, dict) and isinstance(obj.get("counts"), dict):
            return obj["counts"]  # type: ignore[no-any-return]
    return None


class Report:
    """The run's reports, built from the supervisor's state on demand."""

    def __init__(self, cfg: Config, run_dir: Path, out: IO[str], t0: float,
                 core: SupervisorState, ledger_model: RunLedger,
                 snapshot: Callable[[], Snapshot]) -> None:
        self.cfg = cfg
        self.run_dir = run_dir
        self.out = out
        self.t0 = t0
        self.started_ns = time.time_ns()  # wall clock: run.json's label of the start
        self.core = core
        self.ledger_model = ledger_model
        self.snapshot = snapshot
        self._shown: tuple[int, bool] | None = None  # the stats last printed, and stale
        self.reserve = SpaceReserve(run_dir / LEDGER_RESERVE, LEDGER_RESERVE_BYTES)

    def starting(self, processes: int) -> None:
        """The one line while the processes start (stats come seconds later)."""
        self._write(f"{time.monotonic() - self.t0:6.1f}s | starting {processes} processes")

    def notice(self, line: str) -> None:
        """A line that stays on the console (the viewer's address), not one rewritten."""
        self._write(line)
        if self.out.isatty():
            self.out.write("\n")
            self.out.flush()

    def status(self) -> dict[str, Any]:
        """Everything `trapflow status` shows, as JSON-able builtins."""
        h = self.snapshot()
        now = time.monotonic()
        nodes = []
        for c in h.nodes:
            n = self.core.node(c.name)
            nodes.append({"name": c.name, "pid": c.pid,
                          "state": str(n.state), "reason": n.reason,
                          "restarts": n.restart_total, "recycled": n.recycled,
                          "gave_up": n.gave_up,
                          "retries": n.retried, "last_beat_s": round(now - n.last_beat, 1),
                          "counters": c.counters})
        return {
            "run_dir": str(self.run_dir),
            "supervisor_pid": os.getpid(),  # for /metrics' memory by role
            "uptime_s": round(now - self.t0, 1),
            "nodes": nodes,
            "stats": _full_stats(h.stats) if h.stats else None,
            "supervision": self.supervision(),
            "ledger": self.ledger(final=False, snap=h),  # ledger.json so far
            "rig": ({"calib": h.rig.id, "origin": h.rig_origin,
                     **msgspec.structs.asdict(h.rig)} if h.rig is not None else None),
            "ring": ({"segment": h.ring.name, "slots": h.ring.slots, **h.ring.counts()}
                     if h.ring is not None else None),
            "counts": self.counts(),
        }

    def counts(self) -> dict[str, Any] | None:
        """The latest closed interval's visits, MaxN and dwell per label (counts.jsonl), and
        the interval's length; None when the run does not track."""
        ocfg = self.cfg.observe
        if not ocfg.enabled:
            return None
        return {"interval_s": ocfg.interval_s,
                "latest": latest_counts(self.run_dir / ocfg.counts_file)}

    def supervision(self) -> dict[str, Any]:
        """Give-ups, retries and recycles over the run, and their timeline (seconds since
        start); `recycled` per pool, by why (rss, jobs)."""
        core = self.core
        counts = core.counts()
        return {"gave_up": counts["gave_up"], "retries": counts["retry"],
                "capped": counts["capped"], "control": counts["control"],
                "clock_steps": core.clock_steps,
                "recycled": {p: dict(by) for p, by in core.recycled.items()},
                "pools": core.pools.pool_view(), "ladder": core.pools.ladder_view(),
                "timeline": [{"t_s": round(e.t - self.t0, 1), "node": e.node,
                              "kind": e.kind, "reason": e.reason} for e in core.timeline]}

    def _pool_restarts(self, snap: Snapshot) -> dict[str, int]:
        out: dict[str, int] = {}
        for c in snap.nodes:
            if c.pool:
                out[c.pool] = out.get(c.pool, 0) + self.core.node(c.name).restart_total
        return out

    def _stale_s(self, now: float) -> float:
        at = self.ledger_model.stats_at
        return 0.0 if at is None else now - at

    def status_text(self) -> str:
        """One line: time, pairs/s in, per pool processed/s, dropped, restarts."""
        view = self.core.pools.ladder_view()
        level = view["level"] if view is not None and view["index"] else ""
        now = time.monotonic()
        return self.ledger_model.status_text(now - self.t0,
                                             self._pool_restarts(self.snapshot()), level=level,
                                             stale_s=self._stale_s(now))

    def status_line(self) -> None:
        """The status line on the console: rewritten in place on a terminal; elsewhere a
        line only when stats came since the last one (or they turned stale), so a line
        never repeats rates that were not measured again."""
        shown = (self.ledger_model.stats_seen,
                 self._stale_s(time.monotonic()) > status_line.STALE_S)
        if not self.out.isatty() and shown == self._shown:
            return
        self._shown = shown
        self._write(self.status_text())

    def _write(self, line: str) -> None:
        out = self.out
        if out.isatty():
            out.write("\r\x1b[K" + line)
        else:
            out.write(line + "\n")
        out.flush()

    def ledger(self, final: bool = True, snap: Snapshot | None = None) -> dict[str, Any]:
        """Where every pair went: capture's count, then per pool exactly one state each."""
        snap = snap or self.snapshot()
        out = self.ledger_model.ledger({n: p.policy for n, p in self.cfg.pools.items()},
                                       self._pool_restarts(snap), self.supervision(), final,
                                       planned_stop=snap.planned_stop)
        broker = next((c.counters for c in snap.nodes if c.name == "broker"), {})
        gate_s = ((broker["gate_active_s"], broker.get("gate_idle_s", 0))
                  if "gate_active_s" in broker and any(
                      p.gate == "motion" for p in self.cfg.pools.values()) else None)
        out["energy"] = energy_section(self.cfg.energy, snap.cpu_s, time.monotonic() - self.t0,
                                       gate_s)
        norm = next((c.counters for c in snap.nodes if c.name == "normalizer"), {})
        # Lines the normalizer could not write, the disk being full: counted, never silent.
        out["not_written_disk_full"] = {k[len(DISK_FULL_PREFIX):]: n for k, n in
                                        sorted(norm.items()) if k.startswith(DISK_FULL_PREFIX)}
        image = self.ledger_model.stats.image if self.ledger_model.stats else None
        if image is not None:  # capture's image-health watch as it last told (fouling...)
            out["image_health"] = msgspec.structs.asdict(image)  # every field, zeros too
        if self.cfg.modem.enabled:  # what the link carried, refused, aggregated, expired
            modem = next((c.counters for c in snap.nodes if c.name == "modem"), {})
            out["modem"] = dict(sorted(modem.items()))
        return out

    def read_results(self) -> None:
        """Count what results.jsonl gained since the last call (the ledger's truth)."""
        path = self.run_dir / self.cfg.normalizer.results_file
        try:
            with open(path, "rb") as f:
                f.seek(self.ledger_model.delivered.offset)
                self.ledger_model.delivered.feed(f.read(RESULTS_READ_BYTES))
        except FileNotFoundError:
            pass

    def print_totals(self) -> None:
        """At the end: the rest of results.jsonl counted, ledger.json written, the totals
        and the summary printed."""
        out, run_dir, snap = self.out, self.run_dir, self.snapshot()
        if out.isatty():
            out.write("\n")
        for _ in range(RESULTS_READS_AT_END):
            before = self.ledger_model.delivered.offset
            self.read_results()
            if self.ledger_model.delivered.offset == before:
                break
        ledger = self.ledger(snap=snap)
        meta = run_meta.run_metadata(self.cfg, snap.rig, snap.rig_origin, self.started_ns,
                                     time.time_ns(), run_meta.versions(),
                                     duration_s=time.monotonic() - self.t0)
        self.reserve.release()  # the space kept for these two files
        for name, obj in (("ledger.json", ledger), ("run.json", meta)):
            try:  # whole or not at all: a full disk leaves the previous file as it was
                write_atomically(run_dir / name, (json.dumps(obj, indent=1) + "\n").encode())
            except OSError as exc:
                if not is_disk_full(exc):
                    raise
                out.write(f"{name} not written: the disk is full ({exc.strerror})\n")
        if snap.stats is not None:
            out.write(run_ledger.totals_text(ledger))
        if lost := ledger["not_written_disk_full"]:
            out.write("not written, the disk full: " + ", ".join(
                f"{n} lines of {name}" for name, n in lost.items()) + "\n")
        out.write(energy_text(ledger["energy"]))
        c = self.cfg
        out.write("".join(f"{line}\n" for line in run_summary.summary_lines(
            run_dir / c.normalizer.results_file,
            self.ledger_model.delivered.total(), run_dir / c.outbox.path,
            run_dir / c.events.folder if c.events.enabled else None, c.source.kind,
            snap.source_where, c.outbox)))
        out.flush()
