"""A finished run's files as the exports and `trapflow check` read them: whether the run is
still going, and each JSON-lines file read as far as it is whole, with what was cut.

A run still going (its supervisor's lock names a live process) is refused: its files grow
while they are read, and an export of it said "0 media, 0 observations" and exited 0. A
file whose last line was cut mid-way (a power cut while it was appended) is read up to its
last whole line, and the cut is said (`Jsonl.cut`), never skipped without a word.
"""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from trapflow.errors import TrapflowError
from trapflow.normalizer.result_json import line_pool
from trapflow.supervisor.setup import LOCK_FILE, supervisor_alive


class RunInUse(TrapflowError):
    """The run directory is missing, or a run is still going in it (exit status 2)."""


def finished_run(run_dir: Path, what: str) -> None:
    """RunInUse unless run_dir is a directory no live supervisor holds; `what` names the
    command in the message."""
    if not run_dir.is_dir():
        raise RunInUse(f"{what}: expected a run directory, found no directory {run_dir}; name "
                       "the directory a pipeline ran in (its --run-dir)")
    if (run_dir / LOCK_FILE).exists() and supervisor_alive(run_dir):
        pid = (run_dir / LOCK_FILE).read_text(encoding="utf-8", errors="replace").strip()
        raise RunInUse(f"{what}: {run_dir} is a run still going (its supervisor, pid {pid}, "
                       "holds it); run this once it has ended")


@dataclass
class Jsonl:
    """One JSON-lines file: its objects of one kind with their line numbers (from 1), lines
    that are not such an object, and the cut last line, if any."""

    name: str
    exists: bool = False
    items: list[tuple[int, dict[str, Any]]] = field(default_factory=list)
    bad: list[int] = field(default_factory=list)  # whole lines that do not parse
    cut: int | None = None  # the line number of a last line cut mid-way (no newline)

    def bodies(self) -> list[dict[str, Any]]:
        return [body for _n, body in self.items]

    def cut_text(self) -> str:
        """`NAME line N is cut mid-way` when its last line is, else ""."""
        return f"{self.name} line {self.cut} is cut mid-way" if self.cut is not None else ""


def read_jsonl(path: Path, kind: str | None = None) -> Jsonl:
    """A JSON-lines file read line by line: with `kind`, the objects `{kind: {...}}` (their
    bodies); without, every one-key object `{kind: {...}}` whole. A last line without its
    newline that does not parse is the cut, not a bad line."""
    out = Jsonl(path.name)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return out
    out.exists = True
    lines = raw.split(b"\n")
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
            ok = isinstance(obj, dict) and len(obj) == 1
            body = obj.get(kind) if kind is not None and ok else obj
        except ValueError:
            ok, body = False, None
        if ok and isinstance(body, dict):
            out.items.append((n, body))
        elif n == len(lines):  # no newline after it: written in part
            out.cut = n
        elif kind is None or not ok:
            out.bad.append(n)
    return out


def read_json(path: Path) -> dict[str, Any] | None:
    """A JSON object file (ledger.json, run.json), or None when missing or unreadable."""
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return obj if isinstance(obj, dict) else None


@dataclass
class Written:
    """results.jsonl's written results as ledger.json counts them: distinct seqs per pool of
    the ledger, from the lines of the start the ledger tells of (`results_from`)."""

    pools: dict[str, set[int]] = field(default_factory=dict)  # ledger pool -> seqs
    # Seqs no pool of the ledger can be credited with, by what the lines say: "pool X" (a
    # pool the ledger lacks) or a kind (a line without `pool` whose kind no pool, or
    # several, list among their `kinds`).
    unclaimed: dict[str, set[int]] = field(default_factory=dict)
    kinds: dict[str, set[str]] = field(default_factory=dict)  # pool -> kinds of its lines
    first_line: int = 1  # the first line of results.jsonl the ledger's start wrote
    compared: bool = True  # False: a ledger from before pools said their kinds, old lines


def first_line_at(path: Path, offset: int) -> int:
    """The number (from 1) of the line of `path` that starts at byte `offset`."""
    if offset <= 0:
        return 1
    try:
        with path.open("rb") as f:
            return f.read(offset).count(b"\n") + 1
    except OSError:
        return 1


def written(results: Jsonl, ledger: dict[str, Any], first_line: int = 1) -> Written:
    """Each line credited to the pool it names (`pool`, results.jsonl v3); a line of a run
    from before lines named their pool, to the one pool whose `kinds` in ledger.json list its
    kind. Lines before `first_line` are earlier starts' in a reused run directory."""
    pools = {name: p for name, p in (ledger.get("pools") or {}).items() if isinstance(p, dict)}
    makers: dict[str, list[str]] = {}
    listed = True
    for name, p in pools.items():
        if isinstance(p.get("kinds"), list):
            for kind in p["kinds"]:
                makers.setdefault(kind, []).append(name)
        else:
            listed = False
    out = Written(pools={name: set() for name in pools}, first_line=first_line)
    for n, obj in results.items:
        (kind, body), = obj.items()
        if n < first_line or not isinstance(body, dict) or not isinstance(body.get("seq"), int):
            continue
        pool = line_pool(body)
        if pool is not None:
            key = pool if pool in out.pools else f"pool {pool}"
        elif not listed:  # neither the lines nor the ledger say which pool: not compared
            out.compared = False
            continue
        else:
            who = makers.get(kind, [])
            key = who[0] if len(who) == 1 else kind
        (out.pools if key in out.pools else out.unclaimed).setdefault(key, set()).add(
            body["seq"])
        if key in out.pools:
            out.kinds.setdefault(key, set()).add(kind)
    return out


def _ids(ids: list[int]) -> str:
    """Track ids as a short phrase: "track 4", "tracks 3, 4, 5"."""
    shown = ", ".join(map(str, ids[:8])) + (f" and {len(ids) - 8} more" if len(ids) > 8 else "")
    return f"track{'s' if len(ids) > 1 else ''} {shown}"


def damage(run_dir: Path, results_file: str = "results.jsonl",
           tracks_file: str = "tracks.jsonl") -> list[str]:
    """What was cut from a finished run's files and what that leaves out of an export, one
    line each; empty for a whole run. Found: a last line cut mid-way; results.jsonl
    holding fewer results than ledger.json counts for a pool, or ending before the tracks
    do (cut at a line's end); tracks that detection lines carry missing from tracks.jsonl."""
    results, tracks = read_jsonl(run_dir / results_file), read_jsonl(run_dir / tracks_file,
                                                                      "track")
    out: list[str] = []
    if results.cut is not None:
        out.append(f"{results.cut_text()}: that line's result is left out")
    carried: set[int] = set()
    last = ""  # the latest result time ("YYYY-MM-DD HH:MM:SS.mmm" sorts as time)
    for _n, obj in results.items:
        (_kind, body), = obj.items()
        if isinstance(body, dict) and isinstance(body.get("seq"), int):
            last = max(last, str(body.get("timestamp", "")))
            if isinstance(body.get("track"), int):
                carried.add(body["track"])
    ledger = read_json(run_dir / "ledger.json") or {}
    got = written(results, ledger, first_line_at(run_dir / results_file,
                                                 results_from(ledger)))
    for pool, p in sorted((ledger.get("pools") or {}).items()):
        if got.compared and isinstance(p, dict) and isinstance(p.get("processed"), int):
            have = len(got.pools.get(pool, ()))
            if have < p["processed"]:
                out.append(f"{results.name} holds {have} of the {p['processed']} results "
                           f"ledger.json counts for pool {pool}: the pairs of the other "
                           f"{p['processed'] - have} are left out")
    if not tracks.exists:
        return out
    if tracks.cut is not None:
        out.append(f"{tracks.cut_text()}: the track it held is left out")
    have_ids = {b.get("id") for b in tracks.bodies()}
    if missing := sorted(carried - have_ids):
        out.append(f"{tracks.name} lacks {_ids(missing)}, which lines of {results.name} "
                   "carry: their observations are left out")
    end = label_s(last)
    if end is not None:
        after = sorted(b["id"] for b in tracks.bodies() if isinstance(b.get("id"), int)
                       and isinstance(b.get("last_s"), (int, float)) and b["last_s"] > end + 1)
        if after:
            out.append(f"{results.name} ends at {last}, before {_ids(after)} end: the boxes, "
                       "best frames and blanks after it are left out")
    return out


def results_from(ledger: dict[str, Any]) -> int:
    """The byte of results.jsonl where the lines of the start ledger.json tells of begin
    (`results_from`: 0 for a run directory's first start, and for a ledger from before it
    was said)."""
    at = ledger.get("results_from", 0)
    return at if isinstance(at, int) and not isinstance(at, bool) and at > 0 else 0


def label_s(label: Any) -> float | None:
    """A result's timestamp ("YYYY-MM-DD HH:MM:SS.mmm", UTC) in seconds; None if it is not
    one."""
    try:
        t = dt.datetime.strptime(label, "%Y-%m-%d %H:%M:%S.%f")
    except (TypeError, ValueError):
        return None
    return t.replace(tzinfo=dt.timezone.utc).timestamp()
