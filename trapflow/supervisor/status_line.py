"""The console's status line, pure: a run's counters rendered in at most 80 columns with
every pool in it (up to six; beyond, as many as fit and a count of the rest). Owns no
socket; RunLedger.status_text feeds it, the report prints it.

The line is tried in forms from the most spelled out (`mono 2w 14.8/s drop 3`) to the most
compact (`mono 14.8 d3`, names cut to a prefix that stays unique); the first that fits is
shown. Pools keep the order the broker publishes them in (the config's), so a pool never
moves between lines. Stats older than STALE_S are marked: the rates shown are the last
ones measured, not the present's.
"""

from __future__ import annotations

from dataclasses import dataclass

from trapflow.wire.messages import CaptureCounters, PoolStats, Stats
from trapflow.wire.pool_counters import DROPS, counts

# No stats for this long (the broker publishes once a second): the figures are marked stale.
STALE_S = 2.0


@dataclass(frozen=True)
class _Form:
    """How much one rendering spells out."""

    long_head: bool  # "   5.0s | in  15.0/s (30)" rather than "5.0s in 15.0 (30)"
    workers: bool  # "2w" per pool
    flags: str  # "long" (drop 3), "short" (d3), "sum" (!5: problems together), "mark" (!)
    name_cap: int  # pool names cut to this many characters (0: whole), kept unique
    sep: str
    whole: bool = False  # rates rounded to whole pairs/s


_FORMS = (
    _Form(True, True, "long", 0, " | "),
    _Form(True, False, "short", 0, " | "),
    _Form(False, False, "short", 0, " | "),
    _Form(False, False, "short", 6, " "),
    _Form(False, False, "short", 4, " "),
    _Form(False, False, "sum", 4, " "),
    _Form(False, False, "mark", 3, " "),
    _Form(False, False, "mark", 3, " ", whole=True),
)


def _si(n: float) -> str:
    """A count in at most 4 characters: 999, 1.2k, 12k, 120k, 1.2M..."""
    if n < 1000:
        return f"{n:.0f}"
    for unit in "kMGTPE":
        n /= 1000
        if n < 9.95:
            return f"{n:.1f}{unit}"
        if n < 999.5:
            return f"{n:.0f}{unit}"
    return "many"


def _up(up: float) -> str:
    """Time up in at most 6 characters: 12.3s, 0.3h, 27.8h, 116d."""
    if up < 999.95:
        return f"{up:.1f}s"
    return f"{up / 3600:.1f}h" if up < 359_999 else f"{_si(up / 86_400)}d"


def _rate(r: float, whole: bool = False) -> str:
    """A rate in at most 4 characters: 14.8, 148, 1.5k (whole: 15)."""
    return f"{r:.1f}" if r < 99.95 and not whole else _si(r)


def _names(names: list[str], cap: int) -> dict[str, str]:
    """Each name cut to `cap` characters, or longer where a cut would make two alike."""
    if not cap:
        return {n: n for n in names}
    for width in range(cap, max((len(n) for n in names), default=0) + 1):
        cut = {n: n[:width] for n in names}
        if len(set(cut.values())) == len(cut):
            return cut
    return {n: n for n in names}


def _pool(name: str, p: PoolStats, restarts: int, form: _Form, stale: str) -> str:
    problems = (("drop", "d", sum(counts(p, DROPS).values())),
                ("err", "e", p.errors), ("lost", "l", p.lost), ("rst", "r", restarts))
    if form.flags == "long":
        state = "" if p.active else " (inactive)"
        flags = "".join(f" {k} {n}" for k, _, n in problems if n)
        return f"{name}{state} {p.workers}w {p.rate:.1f}/s{stale}{flags}"
    total = sum(n for _, _, n in problems)
    if form.flags == "short":
        flags = "".join(f" {s}{_si(n)}" for _, s, n in problems if n)
    elif form.flags == "sum":
        flags = f" !{_si(total)}" if total else ""
    else:
        flags = "!" if total else ""
    workers = f" {p.workers}w" if form.workers else ""
    if not p.active:  # compact: an inactive pool's rate is no news
        return f"{name}{workers} off{flags}"
    return f"{name}{workers} {_rate(p.rate, form.whole)}{stale}{flags}"


def _head(s: Stats, cap: CaptureCounters, up: float, level: str, stale_s: float,
          form: _Form) -> str:
    stale = stale_s > STALE_S
    if form.long_head:
        head = f"{up:6.1f}s | in {s.rate_in:5.1f}/s{'?' if stale else ''} ({s.pairs_in})"
        if stale:
            head += f" stale {stale_s:.0f}s"
        if level:  # the ladder has stepped down: said before the pools
            head += f" [{level}]"
        if cap.dropped:
            head += f" cap-drop {cap.dropped}"
        if cap.failed:
            head += f" cap-fail {cap.failed}"
        return head
    head = (f"{_up(up)} in {_rate(s.rate_in, form.whole)}{'?' if stale else ''} "
            f"({_si(s.pairs_in)})")
    if stale:
        head += f" stale{stale_s:.0f}s"
    if level:
        head += f" [{level}]"
    if cap.dropped or cap.failed:
        head += f" cap!{_si(cap.dropped + cap.failed)}"
    return head


def render(s: Stats, cap: CaptureCounters, up: float, restarts: dict[str, int],
           width: int, level: str = "", stale_s: float = 0.0) -> str:
    """One line of at most `width` columns: seconds up, pairs/s in (pairs in), then per pool
    its results/s, with drops, failures, losses and restarts only when there are any.
    `stale_s`: seconds since these stats arrived; past STALE_S the rates are marked `?` and
    the head says how old they are."""
    line = ""
    for form in _FORMS:
        # Stale: every figure marked in the long forms; in the compact ones the head says it.
        stale = "?" if stale_s > STALE_S and form.long_head else ""
        names = _names(list(s.pools), form.name_cap)
        parts = [_pool(names[n], p, restarts.get(n, 0), form, stale)
                 for n, p in s.pools.items()]
        head = _head(s, cap, up, level, stale_s, form)
        line = f"{head} | {form.sep.join(parts)}" if parts else head
        if len(line) <= width:
            return line
    # More pools than fit even so: the first that fit, then how many are left out
    # (`trapflow status` shows them all).
    room = width - len(f" +{len(s.pools)} pools")
    line, sep, left = head[:room], " | ", 0
    for part in parts:
        if len(line) + len(sep) + len(part) <= room and not left:
            line += sep + part
            sep = " "
        else:
            left += 1
    return f"{line} +{left} pools" if left else line
