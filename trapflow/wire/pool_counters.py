"""The per-pool counters of PoolStats in one ordered list: what each counts, its unit, how
it adds up over broker restarts, its run-ledger key, label and metric name. The broker's
stats, the run ledger, `trapflow status`, the status line, the viewer's metrics and page,
and the run report derive their lists from here; a unit test holds this list and
PoolStats's fields together."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from trapflow.wire.messages import PoolStats

# procs: worker processes now; flow: pairs that passed a point (received, dispatched);
# drop: pairs the broker ended by dropping them; end: pairs ended otherwise (answered,
# withheld by the gate); lost: pairs that can no longer end; held: pairs held now
# (pending, at a worker, the gate's pre-roll); rate: pairs per second lately; cut: boxes (not
# pairs) cut from results.
Kind = Literal["procs", "flow", "drop", "end", "lost", "held", "rate", "cut"]


@dataclass(frozen=True)
class PoolCounter:
    """One PoolStats field and what every view makes of it."""

    name: str  # the PoolStats field
    kind: Kind
    help: str
    ledger: str = ""  # its key in a pool of ledger.json ("": not a ledger state)
    metric: str = ""  # its Prometheus name part (trapflow_pool_<metric>[_pairs]); "": name
    column: bool = True  # a column of `trapflow status`'s pool table

    @property
    def unit(self) -> str:
        """What it counts: processes, pairs, or pairs per second."""
        return {"procs": "procs", "rate": "pairs/s", "cut": "boxes"}.get(self.kind, "pairs")

    @property
    def label(self) -> str:
        """Its name in a view of the ledger: the ledger key in words ("dropped by policy")."""
        return (self.ledger or self.name).replace("_", " ")

    @property
    def summed(self) -> bool:
        """A count since the run started: the retired brokers' counts add to the live one's
        (a held count or a rate belongs to the live broker alone)."""
        return self.kind in ("flow", "drop", "end", "lost", "cut")

    @property
    def metric_name(self) -> str:
        """The metric's full name: a count of pairs, or a gauge."""
        part = self.metric or self.name
        if self.summed:
            return f"trapflow_pool_{part}_{self.unit}"
        return f"trapflow_pool_{part}"


# In the order of `trapflow status`'s pool table.
POOL_COUNTERS: tuple[PoolCounter, ...] = (
    PoolCounter("workers", "procs", "worker processes connected to the pool"),
    PoolCounter("received", "flow", "pairs that reached the pool"),
    PoolCounter("dispatched", "flow", "pairs given to a worker", column=False),
    PoolCounter("processed", "end", "pairs answered with a result", ledger="processed"),
    PoolCounter("dropped", "drop", "pairs dropped by the pool's policy",
                ledger="dropped_by_policy"),
    PoolCounter("inactive", "drop", "pairs dropped because the pool was deactivated "
                "(trapflow pool --deactivate)", ledger="dropped_inactive"),
    PoolCounter("throttled", "drop", "pairs dropped by the ladder's level: inside the pool's "
                "minimum interval", ledger="dropped_by_level"),
    PoolCounter("stale", "drop", "pairs dropped after waiting longer than the pool's "
                "max_pending_age_s", ledger="dropped_stale"),
    PoolCounter("gated", "end", "pairs withheld by the motion gate (gate: motion): never "
                "given, by design", ledger="gated"),
    PoolCounter("kept", "held", "pairs withheld for now as the gate's pre-roll: fed on "
                "motion, else gated", metric="kept_pairs", column=False),
    PoolCounter("in_flight", "held", "pairs at a worker now", metric="in_flight_pairs"),
    PoolCounter("pending", "held", "pairs waiting for a worker", metric="pending_pairs"),
    PoolCounter("errors", "end", "pairs that failed (bad input, plugin error)",
                ledger="failed", metric="failed"),
    PoolCounter("timed_out", "end", "pairs a worker held longer than the pool's timeout_s",
                ledger="timed_out"),
    PoolCounter("lost", "lost", "pairs whose worker died, or whose broker died holding them",
                ledger="lost"),
    PoolCounter("cut", "cut", "detections cut from results beyond the pool's max_detections "
                "(the least confident)", ledger="boxes_cut"),
    PoolCounter("rate", "rate", "pairs processed per second over the last interval",
                metric="rate_pairs_per_second"),
)

# The ledger's two states of a pair that no counter holds: on its way when the run stopped
# as planned (ledger.json at the end), or on its way now (the ledger while the run goes on).
UNFINISHED = "unfinished_at_stop"
IN_PROGRESS = "in_progress"
# Every state a pool of a ledger can give a pair, as (ledger key, label), in the order the
# views show them: the report, the viewer's page and the totals derive their rows from it,
# so that a new counter shows everywhere at once.
LEDGER_STATES: tuple[tuple[str, str], ...] = (
    *((c.ledger, c.label) for c in POOL_COUNTERS if c.ledger),
    (UNFINISHED, "unfinished at stop"),
    (IN_PROGRESS, "in progress"),
)

# Counts since the run started, summed over broker restarts.
SUMMED = tuple(c.name for c in POOL_COUNTERS if c.summed)
# The states a pair ends in at a pool, lost aside: each pair is in at most one.
SETTLED = tuple(c.name for c in POOL_COUNTERS if c.kind in ("drop", "end"))
# The ways the broker drops a pair.
DROPS = tuple(c.name for c in POOL_COUNTERS if c.kind == "drop")


def settled(p: PoolStats, processed: int | None = None) -> int:
    """Pairs of a pool in a final state but lost; `processed`: the results counted
    elsewhere (results.jsonl) in place of the broker's count."""
    total = sum(int(getattr(p, name)) for name in SETTLED)
    return total if processed is None else total - p.processed + processed


def counts(p: PoolStats, names: tuple[str, ...]) -> dict[str, int]:
    """The named counters of a pool."""
    return {name: getattr(p, name) for name in names}
