"""The run ledger, pure: where every pair went, across broker and capture restarts, and the
one model the status line, `trapflow status` and ledger.json render.

Each broker and each capture process counts only what it saw. When a broker dies, its
last published counters are kept; what it still held (pending or in flight) can never
finish, so it counts as lost. When a capture dies, its last reported counters are kept and
its successor numbers pairs past them. A pair a pool's motion gate withheld is `gated`, a
state of its own (never dropped, never lost). verdict() reads the totals at the end: whether the
run failed (exit status 1) and the line that says why.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import msgspec

from trapflow.supervisor import status_line
from trapflow.wire.messages import FAILED_PREFIX, CaptureCounters, PoolStats, Stats
from trapflow.wire.pool_counters import IN_PROGRESS, POOL_COUNTERS, SUMMED, UNFINISHED, settled

__all__ = ["UNFINISHED", "Delivered", "RunLedger", "capture_failures", "combine", "retire",
           "verdict"]

# The normalizer's heartbeat counters route:<pool>:<kind> say which pool's results become lines
# of which kind (the first key of a results.jsonl line): ledger.json's `kinds` of a pool. A
# line names its pool itself (`pool`, results.jsonl v3); the routes credit the lines of a
# normalizer from before that, by kind, to the one pool that makes it.
ROUTE_PREFIX = "route:"
# The console's width: the status line never wraps on an 80-column terminal.
STATUS_WIDTH = 80
# Seqs remembered per kind to count a result written twice (resent to a restarted
# normalizer before it acknowledged) once; resends are never further apart than this.
RECENT_SEQS = 65536


class _Line(msgspec.Struct):
    seq: int = -1
    pool: str | None = None  # result_json.POOL_KEY; None on a line of v2 and before


_line_dec = msgspec.json.Decoder(dict[str, _Line])


class Delivered:
    """Distinct results per pool in results.jsonl, fed its bytes as they are appended.

    The results file is what was delivered: counting it (not what a dead broker or
    normalizer last reported) makes the ledger agree with it pair by pair after kills.
    A result of several lines (one per detection) counts once; so does one written twice.
    Each line counts for the pool it names; a line that names none (a normalizer from
    before lines did) counts for its kind, credited to a pool by the routes (by_pool).
    """

    def __init__(self) -> None:
        self.pools: dict[str, int] = {}  # distinct results per pool, of lines naming it
        self.kinds: dict[str, int] = {}  # distinct results per kind, of lines naming no pool
        self.offset = 0  # bytes of the file consumed (whole lines only)
        self.unreadable = 0  # lines that are not a result (a torn write after a power cut)
        self._recent: dict[tuple[bool, str], tuple[set[int], deque[int]]] = {}
        self._tail = b""

    def feed(self, data: bytes) -> None:
        """More bytes of the file, from where the last call ended."""
        data = self._tail + data
        end = data.rfind(b"\n") + 1
        self._tail = data[end:]
        self.offset += end
        for line in data[:end].splitlines():
            if line:
                self._count(line)

    def _count(self, line: bytes) -> None:
        try:
            obj = _line_dec.decode(line)
        except (msgspec.DecodeError, msgspec.ValidationError):
            self.unreadable += 1
            return
        for kind, item in obj.items():
            named = item.pool is not None
            key = item.pool if item.pool is not None else kind
            seen, order = self._recent.setdefault((named, key), (set(), deque()))
            if item.seq in seen:
                return
            seen.add(item.seq)
            order.append(item.seq)
            if len(order) > RECENT_SEQS:
                seen.discard(order.popleft())
            counts = self.pools if named else self.kinds
            counts[key] = counts.get(key, 0) + 1
            return

    def total(self) -> int:
        """Distinct results written (the end summary's count)."""
        return sum(self.pools.values()) + sum(self.kinds.values())

    def by_pool(self, routes: dict[str, set[str]]) -> dict[str, int]:
        """Counts per pool: the lines that name it, and those naming none of a kind that
        this pool alone is routed (pool -> kinds); a kind two pools make is nobody's then.
        A pool is absent until a line counts for it or it is routed."""
        makers: dict[str, list[str]] = {}
        for pool, kinds in routes.items():
            for kind in kinds:
                makers.setdefault(kind, []).append(pool)
        out = dict(self.pools)
        for pool in routes:
            out.setdefault(pool, 0)
        for kind, n in self.kinds.items():
            who = makers.get(kind, [])
            if len(who) == 1:
                out[who[0]] += n
        return out


def routes_of(counters: dict[str, int]) -> dict[str, set[str]]:
    """pool -> the kinds its results became, from the normalizer's route:<pool>:<kind>
    counters (two pools of one plugin: both list its kind)."""
    out: dict[str, set[str]] = {}
    for key in counters:
        if key.startswith(ROUTE_PREFIX):
            pool, _, kind = key[len(ROUTE_PREFIX):].partition(":")
            out.setdefault(pool, set()).add(kind)
    return out


def retire(last: Stats) -> Stats:
    """The final counters of a broker that died: what it held is lost, but for what its
    gate kept as pre-roll: withheld, and never given now, that is gated."""
    pools = {name: msgspec.structs.replace(
        p, lost=p.lost + p.pending + p.in_flight, pending=0, in_flight=0, workers=0, rate=0.0,
        gated=p.gated + p.kept, kept=0)
        for name, p in last.pools.items()}
    return msgspec.structs.replace(last, pools=pools, rate_in=0.0)


def combine(base: Stats | None, cur: Stats) -> Stats:
    """Counters of retired brokers (base) added to the live broker's (cur)."""
    if base is None:
        return cur
    pools: dict[str, PoolStats] = {}
    for name in {*base.pools, *cur.pools}:
        a, b = base.pools.get(name, PoolStats()), cur.pools.get(name, PoolStats())
        summed = {k: getattr(a, k) + getattr(b, k) for k in SUMMED}
        failures = dict(a.failures)
        for kind, n in b.failures.items():
            failures[kind] = failures.get(kind, 0) + n
        pools[name] = msgspec.structs.replace(b, failures=failures, **summed)
    return msgspec.structs.replace(cur, pairs_in=base.pairs_in + cur.pairs_in,
                                   malformed=base.malformed + cur.malformed, pools=pools)


def capture_failures(capture: dict[str, int]) -> dict[str, int]:
    """Pairs skipped at capture by kind (unreadable, truncated, size, too_large...)."""
    return {k[len(FAILED_PREFIX):]: n for k, n in sorted(capture.items())
            if k.startswith(FAILED_PREFIX) and n}


def verdict(source: str, capture: dict[str, int], gave_up: str | None, finished: bool,
            stats: Stats | None) -> list[str]:
    """Why a run failed, one phrase per cause; empty when it did not.

    A finite source that could not go on (gave_up: its reason), one that ended having read
    no pair at all, and a pool that failed every pair it was given (and processed none).
    """
    problems = []
    if gave_up is not None:
        problems.append(f"source {source} could not go on: "
                        f"{gave_up.removeprefix('source failed: ')}")
    elif finished and capture.get("produced", 0) == 0 and capture.get("failed", 0) > 0:
        kinds = ", ".join(f"{k} {n}" for k, n in capture_failures(capture).items())
        problems.append(f"source {source}: none of its {capture['failed']} pairs could be "
                        f"read ({kinds}); see trapflow.log")
    for name, p in sorted(stats.pools.items() if stats else ()):
        # Failed, not timed out: a pool that only ran out of time is slow, not broken.
        if p.errors and p.processed == 0:
            kinds = ", ".join(f"{k} {n}" for k, n in p.failures.items())
            problems.append(f"pool {name} failed every pair it was given ({p.errors}"
                            f"{f': {kinds}' if kinds else ''}); see trapflow.log")
    return problems


@dataclass
class RunLedger:
    """The run's counters as the supervisor learns them: broker stats and capture counters,
    with what dead brokers and captures had counted kept."""

    stats: Stats | None = None  # the run's totals, all brokers
    _broker: Stats | None = None  # the live broker's own
    _retired: Stats | None = None  # what brokers that died had counted
    _capture_base: CaptureCounters = field(default_factory=CaptureCounters)
    _capture: CaptureCounters | None = None  # the live capture's own
    seen_capture: bool = False
    delivered: Delivered = field(default_factory=Delivered)  # results.jsonl, as written
    routes: dict[str, set[str]] = field(default_factory=dict)  # pool -> its result kinds
    # The byte of results.jsonl where this start's lines begin: 0, or its size when the run
    # directory held a results.jsonl (a start after a power cut or a stop): ledger.json's
    # counts are this start's, and `trapflow check` compares them with the lines from here.
    results_from: int = 0
    # Pairs the brokers had counted lost, per pool, when a planned stop began: what they
    # count lost after it (workers told to leave, a queue never served) is the stop's doing.
    lost_at_stop: dict[str, int] | None = None
    stats_at: float | None = None  # monotonic time the last stats arrived
    stats_seen: int = 0  # stats received so far

    # --- events ---------------------------------------------------------------------

    def on_stats(self, stats: Stats, now: float | None = None) -> None:
        self._broker = stats
        self.stats_at = now
        self.stats_seen += 1
        self.stats = combine(self._retired, stats)

    def on_capture(self, counters: CaptureCounters) -> None:
        self._capture = counters
        self.seen_capture = True

    def on_normalizer(self, counters: dict[str, int]) -> None:
        for pool, kinds in routes_of(counters).items():
            self.routes.setdefault(pool, set()).update(kinds)

    def stopping(self) -> None:
        """A planned stop begins (before any process is told): keep what was lost so far.
        The brokers' stats are at most a stats interval old: a pair lost to a crash in that
        last interval is reported unfinished at stop."""
        self.lost_at_stop = {n: p.lost for n, p in (self.stats.pools.items()
                                                     if self.stats else ())}

    def retire_broker(self) -> None:
        """A restarted broker counts from zero: the run's totals keep what it saw."""
        if self._broker is not None:
            self._retired = combine(self._retired, retire(self._broker))
            self._broker = None

    def retire_capture(self, margin: int) -> int:
        """A capture died: keep its counters; return the seq its successor starts from,
        `margin` past the last one it reported (a pool sees a gap, never a repeated seq)."""
        last = self._capture or CaptureCounters()
        self._capture_base = self._capture_base + last
        self._capture = None
        return self._capture_base.next_seq + margin

    # --- read-outs ------------------------------------------------------------------

    def capture(self) -> CaptureCounters:
        """Capture's counters over the whole run, across its restarts."""
        return self._capture_base + (self._capture or CaptureCounters())

    def capture_counts(self) -> dict[str, int]:
        """The same as flat counters (produced, dropped, failed, failed_<kind>...)."""
        c = self.capture()
        out = {"produced": c.produced, "dropped": c.dropped, "failed": c.failed,
               "source_errors": c.source_errors}
        out.update({f"{FAILED_PREFIX}{k}": n for k, n in c.failures.items()})
        return dict(sorted(out.items()))

    def produced(self) -> int:
        """Pairs capture sent: what it reported, or, when a capture was killed before
        reporting its last pairs, what demonstrably existed: what reached the brokers, or
        what one pool accounts for (results written, dropped, timed out, failed)."""
        s = self.stats
        if s is None:
            return self.capture().produced
        delivered = self.delivered.by_pool(self.routes)
        accounted = [settled(p, delivered.get(n)) for n, p in s.pools.items()]
        return max(self.capture().produced, s.pairs_in, *accounted)

    def drained(self) -> bool:
        """Every pair capture produced reached the broker and left every pool, and every
        result a broker answered is in results.jsonl: a normalizer that lags behind the
        pools is waited for (within the drain's time), not cut off (issue 36 item 1)."""
        s = self.stats
        produced = self.capture().produced if self.seen_capture else -1
        written = self.delivered.by_pool(self.routes)
        return (s is not None and s.pairs_in >= produced
                and all(p.pending == 0 and p.in_flight == 0
                        and written.get(name, 0) >= p.processed
                        for name, p in s.pools.items()))

    def ledger(self, policies: dict[str, str], restarts: dict[str, int],
               supervision: dict[str, Any] | None = None, final: bool = True,
               planned_stop: bool = False) -> dict[str, Any]:
        """Where every pair went: capture's count, then per pool exactly one state each;
        restarts per pool and the supervision timeline (give-ups, retries).

        While the run goes on (not final), every pair not in a state and not counted lost by
        a broker is in progress: on the capture link, pending, at a worker, or answered and
        on its way to results.jsonl (a dead broker's pending and in-flight pairs are counted
        lost when it is retired). At its end they can no longer finish: after a planned stop
        (duration, a stop request, a signal, a drained source) those that no broker counted
        as lost were merely on their way (capture link, queue, worker, normalizer) and are
        "unfinished at stop", counted apart; after a failure they are lost. A pair a broker
        answered whose result never reached results.jsonl (the normalizer could not keep
        up, and the broker's queue to it ended with the broker) is lost either way, and
        counted in `unwritten` too: a stop never hides a normalizer that fell behind
        (issue 36 item 1: 87 of 602 results written, "lost 0")."""
        s = self.stats
        produced = self.produced()
        out = self._head(produced)
        delivered = self.delivered.by_pool(self.routes)
        for name, p in (s.pools.items() if s else ()):
            # Processed: the results written for this pool (known once its results are
            # routed); lost: whatever else is not in a state, as the brokers counted them.
            written = delivered.get(name)
            processed = p.processed if written is None else written
            unwritten = 0 if written is None else max(0, p.processed - written)
            rest = max(0, produced - settled(p, processed))
            in_progress = self._unfinished(name, p, rest, unwritten, final, planned_stop)
            states = {c.ledger: getattr(p, c.name) for c in POOL_COUNTERS if c.ledger}
            out["pools"][name] = {
                **states, "processed": processed, "lost": rest - in_progress,
                "policy": policies.get(name, ""), "failures": p.failures,
                "restarts": restarts.get(name, 0),
                # Of those lost (or, live, in progress): answered, not (yet) written.
                "unwritten": unwritten,
                # Replaced on purpose (max_rss_mb, max_jobs), by why; not restarts.
                "recycled": dict((supervision or {}).get("recycled", {}).get(name, {})),
                # The results.jsonl kinds its results became (`trapflow check` credits a
                # line that names no pool by them).
                "kinds": sorted(self.routes.get(name, ())),
            }
            if not final:
                out["pools"][name][IN_PROGRESS] = in_progress
            elif planned_stop:
                out["pools"][name][UNFINISHED] = in_progress
        if supervision is not None:
            out["supervision"] = supervision
        return out

    def _head(self, produced: int) -> dict[str, Any]:
        """The ledger's counts before the pools: capture's and the broker's."""
        cap = self.capture()
        return {
            "produced": produced,
            "dropped_at_capture": cap.dropped,  # the broker was not reading
            # Read but never sent: unreadable, cut short, two sizes, too large for the ring.
            "failed_at_capture": cap.failed,
            "capture_failures": {k: n for k, n in sorted(cap.failures.items()) if n},
            "reached_broker": self.stats.pairs_in if self.stats else 0,
            # This start's lines of results.jsonl begin at this byte (a reused run directory
            # holds earlier starts' lines before it); every count here is this start's.
            "results_from": self.results_from,
            "pools": {},
        }

    def _unfinished(self, name: str, p: PoolStats, rest: int, unwritten: int, final: bool,
                    planned_stop: bool) -> int:
        """Of a pool's `rest` (pairs in no state), those still on their way: the others
        are lost (ledger's docstring)."""
        if not final:  # only what a broker counted lost is lost while the run goes on
            # (pending, in flight, kept as the gate's pre-roll, on a link: in progress)
            return rest - min(rest, p.lost)
        if planned_stop:  # what no broker had counted lost when the stop began
            lost = p.lost if self.lost_at_stop is None else self.lost_at_stop.get(name, 0)
            return rest - min(rest, lost + unwritten)
        return 0

    def status_text(self, up: float, restarts: dict[str, int], width: int = STATUS_WIDTH,
                    level: str = "", stale_s: float = 0.0) -> str:
        """One line of at most `width` columns with every pool (trapflow.supervisor.
        status_line); `stale_s`: seconds since the last stats arrived. A degraded ladder
        `level` is shown after the input rate."""
        if self.stats is None:
            return f"{up:6.1f}s | waiting for stats"[:width]
        return status_line.render(self.stats, self.capture(), up, restarts, width,
                                  level=level, stale_s=stale_s)


def unwritten_text(pool: dict[str, Any]) -> str:
    """ " (N answered, never written)" when the normalizer fell behind, else ""."""
    n = min(int(pool.get("unwritten", 0)), int(pool["lost"]))
    return f" ({n} answered, never written)" if n else ""


def totals_text(ledger: dict[str, Any]) -> str:
    """The end-of-run summary of a ledger, one line per pool."""
    failed = ledger["failed_at_capture"]
    kinds = ", ".join(f"{k} {v}" for k, v in ledger["capture_failures"].items())
    lines = [f"totals: {ledger['produced']} pairs captured, "
             f"{ledger['reached_broker']} reached the broker"
             f"{f', {failed} failed at capture ({kinds})' if failed else ''}"]
    for name, p in ledger["pools"].items():
        kinds = ", ".join(f"{k} {v}" for k, v in p["failures"].items())
        going = f"in progress {p[IN_PROGRESS]}, " if IN_PROGRESS in p else ""
        if UNFINISHED in p:
            going = f"unfinished at stop {p[UNFINISHED]}, "
        inactive = f", inactive {p['dropped_inactive']}" if p.get("dropped_inactive") else ""
        if p.get("dropped_by_level"):
            inactive += f", by level {p['dropped_by_level']}"
        if p.get("dropped_stale"):
            inactive += f", stale {p['dropped_stale']}"
        if p.get("gated"):
            inactive += f", gated {p['gated']}"
        recycled = sum(p.get("recycled", {}).values())
        lines.append(
            f"  {name}: processed {p['processed']}, dropped {p['dropped_by_policy']} "
            f"({p['policy']}){inactive}, timed out {p['timed_out']}, failed {p['failed']}"
            f"{f' ({kinds})' if kinds else ''}, lost {p['lost']}"
            f"{unwritten_text(p) if 'unwritten' in p and p['lost'] else ''}, {going}"
            f"restarts {p['restarts']}{f', recycled {recycled}' if recycled else ''}")
    sup = ledger.get("supervision")
    if sup and (sup["gave_up"] or sup["retries"]):
        lines.append(f"  supervision: {sup['gave_up']} give-ups, {sup['retries']} retries")
    ladder = sup.get("ladder") if sup else None
    if ladder and ladder.get("changes"):
        lines.append(f"  ladder: {ladder['changes']} level changes, at {ladder['level']} "
                     f"({ladder['reason']})")
    return "\n".join(lines) + "\n"
