"""What a run reports while it runs and when it ends: the status reply, the status line,
ledger.json and the totals. Owns no socket; reads results.jsonl (the ledger's truth).
The counting is trapflow.supervisor.ledger's; this reads the supervisor through ReportHost.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Protocol

import msgspec

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import Config
from trapflow.supervisor import ledger as run_ledger
from trapflow.supervisor import summary as run_summary
from trapflow.supervisor.ledger import RunLedger
from trapflow.supervisor.state import SupervisorState
from trapflow.wire import messages
from trapflow.wire.frame_ring import FrameRing

if TYPE_CHECKING:
    from trapflow.supervisor.shell import Child

# results.jsonl is read incrementally for the ledger, at most this much per status tick.
RESULTS_READ_BYTES = 4 << 20
RESULTS_READS_AT_END = 10_000


class ReportHost(Protocol):
    """What a report reads of the supervisor (trapflow.supervisor.shell.Supervisor)."""

    cfg: Config
    run_dir: Path
    out: IO[str]
    t0: float
    children: list[Child]
    core: SupervisorState
    ledger_model: RunLedger
    planned_stop: bool
    rig: StereoRig | None
    rig_origin: str
    source_where: str
    ring: FrameRing | None

    @property
    def stats(self) -> messages.Stats | None: ...


def _full_stats(stats: messages.Stats) -> dict[str, Any]:
    """Stats as plain data with every field, zeros included (the wire form omits them)."""
    out = msgspec.structs.asdict(stats)
    out["pools"] = {n: msgspec.structs.asdict(p) for n, p in stats.pools.items()}
    return out


class Report:
    """The run's reports, built from the supervisor's state on demand."""

    def __init__(self, host: ReportHost) -> None:
        self.host = host

    def status(self) -> dict[str, Any]:
        """Everything `trapflow status` shows, as JSON-able builtins."""
        h = self.host
        now = time.monotonic()
        nodes = []
        for c in h.children:
            n = h.core.node(c.name)
            nodes.append({"name": c.name, "pid": c.proc.pid if c.proc else None,
                          "state": str(n.state), "reason": n.reason,
                          "restarts": n.restart_total, "recycled": n.recycled,
                          "gave_up": n.gave_up,
                          "retries": n.retried, "last_beat_s": round(now - n.last_beat, 1),
                          "counters": c.counters})
        return {
            "run_dir": str(h.run_dir),
            "uptime_s": round(now - h.t0, 1),
            "nodes": nodes,
            "stats": _full_stats(h.stats) if h.stats else None,
            "supervision": self.supervision(),
            "ledger": self.ledger(final=False),  # ledger.json so far
            "rig": ({"calib": h.rig.id, "origin": h.rig_origin,
                     **msgspec.structs.asdict(h.rig)} if h.rig is not None else None),
            "ring": ({"segment": h.ring.name, "slots": h.ring.slots, **h.ring.counts()}
                     if h.ring is not None else None),
        }

    def supervision(self) -> dict[str, Any]:
        """Give-ups, retries and recycles over the run, and their timeline (seconds since
        start); `recycled` per pool, by why (rss, jobs)."""
        core = self.host.core
        counts = core.counts()
        return {"gave_up": counts["gave_up"], "retries": counts["retry"],
                "capped": counts["capped"], "control": counts["control"],
                "recycled": {p: dict(by) for p, by in core.recycled.items()},
                "pools": core.pool_view(), "ladder": core.ladder_view(),
                "timeline": [{"t_s": round(e.t - self.host.t0, 1), "node": e.node,
                              "kind": e.kind, "reason": e.reason} for e in core.timeline]}

    def _pool_restarts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for c in self.host.children:
            if c.spec.pool:
                out[c.spec.pool] = (out.get(c.spec.pool, 0)
                                    + self.host.core.node(c.name).restart_total)
        return out

    def status_text(self) -> str:
        """One line: time, pairs/s in, per pool processed/s, dropped, restarts."""
        h = self.host
        view = h.core.ladder_view()
        level = view["level"] if view is not None and view["index"] else ""
        return h.ledger_model.status_text(time.monotonic() - h.t0, self._pool_restarts(),
                                          level=level)

    def status_line(self) -> None:
        """The status line on the console: rewritten in place on a terminal."""
        line = self.status_text()
        out = self.host.out
        if out.isatty():
            out.write("\r\x1b[K" + line)
        else:
            out.write(line + "\n")
        out.flush()

    def ledger(self, final: bool = True) -> dict[str, Any]:
        """Where every pair went: capture's count, then per pool exactly one state each."""
        h = self.host
        return h.ledger_model.ledger({n: p.policy for n, p in h.cfg.pools.items()},
                                     self._pool_restarts(), self.supervision(), final,
                                     planned_stop=h.planned_stop)

    def read_results(self) -> None:
        """Count what results.jsonl gained since the last call (the ledger's truth)."""
        h = self.host
        path = h.run_dir / h.cfg.normalizer.results_file
        try:
            with open(path, "rb") as f:
                f.seek(h.ledger_model.delivered.offset)
                h.ledger_model.delivered.feed(f.read(RESULTS_READ_BYTES))
        except FileNotFoundError:
            pass

    def print_totals(self) -> None:
        """At the end: the rest of results.jsonl counted, ledger.json written, the totals
        and the summary printed."""
        h = self.host
        if h.out.isatty():
            h.out.write("\n")
        for _ in range(RESULTS_READS_AT_END):
            before = h.ledger_model.delivered.offset
            self.read_results()
            if h.ledger_model.delivered.offset == before:
                break
        ledger = self.ledger()
        (h.run_dir / "ledger.json").write_text(json.dumps(ledger, indent=1) + "\n")
        if h.stats is not None:
            h.out.write(run_ledger.totals_text(ledger))
        c = h.cfg
        h.out.write("".join(f"{line}\n" for line in run_summary.summary_lines(
            h.run_dir / c.normalizer.results_file,
            sum(h.ledger_model.delivered.counts.values()), h.run_dir / c.outbox.path,
            h.run_dir / c.events.folder if c.events.enabled else None, c.source.kind,
            h.source_where, c.outbox)))
        h.out.flush()
