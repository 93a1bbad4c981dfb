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
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar

from trapflow.errors import TrapflowError
from trapflow.supervisor.setup import LOCK_FILE, supervisor_alive
from trapflow.wire.result_lines import (
    CountsLine,
    LineError,
    MonoIRLine,
    OtherKind,
    ResultLine,
    TrackLine,
    decode_counts,
    decode_result,
    decode_track,
)


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


T = TypeVar("T")


@dataclass
class Jsonl(Generic[T]):
    """One JSON-lines file: its lines of one kind, decoded, with their line numbers (from
    1), lines that are not such a line (and what was wrong with each), and the cut last
    line, if any."""

    name: str
    exists: bool = False
    items: list[tuple[int, T]] = field(default_factory=list)
    bad: list[int] = field(default_factory=list)  # whole lines that do not decode
    why: dict[int, str] = field(default_factory=dict)  # bad line -> what was wrong
    cut: int | None = None  # the line number of a last line cut mid-way (no newline)

    def bodies(self) -> list[T]:
        return [body for _n, body in self.items]

    def cut_text(self) -> str:
        """`NAME line N is cut mid-way` when its last line is, else ""."""
        return f"{self.name} line {self.cut} is cut mid-way" if self.cut is not None else ""


def _read(path: Path, decode: Callable[[bytes, str], T]) -> Jsonl[T]:
    """A JSON-lines file decoded line by line (`decode` raises LineError naming the line;
    OtherKind for a line of another kind, passed by). A last line without its newline that
    is not JSON is the cut, not a bad line."""
    out: Jsonl[T] = Jsonl(path.name)
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
            out.items.append((n, decode(line, f"{path.name} line {n}")))
        except OtherKind:
            continue
        except LineError as exc:
            if n == len(lines) and not _is_json(line):  # no newline after it: written in part
                out.cut = n
            else:
                out.bad.append(n)
                out.why[n] = str(exc)
    return out


def _is_json(line: bytes) -> bool:
    try:
        json.loads(line)
    except ValueError:
        return False
    return True


def _record(line: bytes, where: str) -> dict[str, Any]:
    obj = json.loads(line) if _is_json(line) else None
    if not isinstance(obj, dict) or len(obj) != 1:
        raise LineError(f"{where}: expected a JSON object of one kind")
    return obj


def read_jsonl(path: Path) -> Jsonl[dict[str, Any]]:
    """A JSON-lines file of records `{kind: {...}}` other than the run's own lines (a
    surface file: the modem's records), each whole."""
    return _read(path, _record)


def read_results(path: Path) -> Jsonl[ResultLine]:
    """results.jsonl, each line typed (trapflow.wire.result_lines)."""
    return _read(path, decode_result)


def read_tracks(path: Path) -> Jsonl[TrackLine]:
    """tracks.jsonl, each line's track typed."""
    return _read(path, decode_track)


def read_counts(path: Path) -> Jsonl[CountsLine]:
    """counts.jsonl, each line's interval typed."""
    return _read(path, decode_counts)


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


def written(results: Jsonl[ResultLine], ledger: dict[str, Any], first_line: int = 1) -> Written:
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
    for n, line in results.items:
        if n < first_line:
            continue
        kind, body = line
        pool = line.pool
        if pool is not None:
            key = pool if pool in out.pools else f"pool {pool}"
        elif not listed:  # neither the lines nor the ledger say which pool: not compared
            out.compared = False
            continue
        else:
            who = makers.get(kind, [])
            key = who[0] if len(who) == 1 else kind
        (out.pools if key in out.pools else out.unclaimed).setdefault(key, set()).add(
            body.seq)
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
    results, tracks = read_results(run_dir / results_file), read_tracks(run_dir / tracks_file)
    out: list[str] = []
    if results.cut is not None:
        out.append(f"{results.cut_text()}: that line's result is left out")
    carried: set[int] = set()
    last = ""  # the latest result time ("YYYY-MM-DD HH:MM:SS.mmm" sorts as time)
    for _n, (_kind, body) in results.items:
        last = max(last, body.timestamp)
        if isinstance(body, MonoIRLine) and isinstance(body.track, int):
            carried.add(body.track)
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
    have_ids = {b.id for b in tracks.bodies()}
    if missing := sorted(carried - have_ids):
        out.append(f"{tracks.name} lacks {_ids(missing)}, which lines of {results.name} "
                   "carry: their observations are left out")
    end = label_s(last)
    if end is not None:
        after = sorted(b.id for b in tracks.bodies() if b.last_s > end + 1)
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
