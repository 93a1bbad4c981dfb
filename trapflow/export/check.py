"""`trapflow check RUN_DIR`, pure but for reading the run's files: whether the files a
finished run leaves tell one story, one line per disagreement naming the file, the line or
id, and both numbers.

What must agree:

- ledger.json and results.jsonl: each pool's `processed` is the number of distinct seqs
  among the lines that name it (`pool`; two pools may run one plugin, so a line's kind does
  not say its pool); `processed` is the one ledger state that counts written lines (the
  others count pairs that wrote none: dropped, gated, failed, timed out, lost, unfinished),
  so it is the one compared. Lines of a run from before lines named their pool are credited
  by kind: to the one pool whose `kinds` in ledger.json list it. A run directory used again
  (a start after a power cut, or after a clean stop) holds every start's lines, and its
  ledger.json counts the last start's: they are compared with the lines from the byte it
  names (`results_from`) on; the tracks and counts checks read every line.
- results.jsonl and tracks.jsonl: every track id a detection line carries is a track of
  tracks.jsonl; the track's label is the one most of its lines carry (allowing for its
  first boxes, written before it was confirmed and without its id); each line's time lies
  within the track's first and last time.
- counts.jsonl and the tracks: per interval and label, visits are the tracks first seen
  (with their id) in it, and MaxN the most tracks of that label on one pair's lines
  (tracking/counts.py's definitions; a track's label is its tracks.jsonl label).
- a surface file (`--surface`): each record the surface wrote is a line the box wrote: a
  result line (kind, seq, time, label, track), a track (id, label, start), an interval's
  counts (start, pairs, visits and MaxN per label), or news of a label the tracks carry.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from msgspec import UNSET

from trapflow.export.run_files import (
    Jsonl,
    first_line_at,
    label_s,
    read_counts,
    read_json,
    read_jsonl,
    read_results,
    read_tracks,
    results_from,
    written,
)
from trapflow.wire.result_lines import (
    CountsLine,
    MonoIRLine,
    ResultItem,
    ResultLine,
    TrackLine,
)

# Result times are written to the millisecond, tracks' and counts' to 3 decimals.
TIME_TOL_S = 0.002
# A track's span is its measured duration named on the wall clock at its end: a wall clock
# slewed while it lasted (NTP, at most 500 ppm) moves its lines this share of it.
SLEW = 0.001


def _secs(t_s: float) -> str:
    """Whole seconds as the modem carries them (tracking/stage.py's modem records)."""
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(t_s))


@dataclass
class _Run:
    """What the checks need of the run's files."""

    results: Jsonl[ResultLine]
    tracks: Jsonl[TrackLine]
    counts: Jsonl[CountsLine]
    ledger: dict[str, Any] | None
    seqs: dict[str, set[int]] = field(default_factory=dict)  # kind -> distinct seqs
    # Detection lines with a track: (line number, seq, time, label, track id).
    tracked: list[tuple[int, int, float, str, int]] = field(default_factory=list)
    by_id: dict[int, tuple[int, TrackLine]] = field(default_factory=dict)


def _load(run_dir: Path, results_file: str, tracks_file: str, counts_file: str,
          out: list[str]) -> _Run:
    run = _Run(read_results(run_dir / results_file), read_tracks(run_dir / tracks_file),
               read_counts(run_dir / counts_file), read_json(run_dir / "ledger.json"))
    files: tuple[Jsonl[Any], ...] = (run.results, run.tracks, run.counts)
    for f in files:
        out += [f"{f.why[n]} (not a line of the run)" for n in f.bad]
        if f.cut is not None:
            out.append(f"{f.cut_text()}: it holds no whole line there")
    if not run.results.exists:
        out.append(f"{results_file}: missing; a finished run always leaves it")
    for n, (kind, item) in run.results.items:
        run.seqs.setdefault(kind, set()).add(item.seq)
        t = label_s(item.timestamp)
        if isinstance(item, MonoIRLine) and isinstance(item.track, int) and t is not None:
            run.tracked.append((n, item.seq, t, item.label, item.track))
    for n, body in run.tracks.items:
        tid = body.id
        if tid in run.by_id:
            out.append(f"{run.tracks.name} line {n}: track {tid} again (first at line "
                       f"{run.by_id[tid][0]})")
        else:
            run.by_id[tid] = (n, body)
    return run


def _ledger(run: _Run, results_path: Path, out: list[str]) -> None:
    """Each pool's processed against the distinct seqs of the lines credited to it
    (run_files.written: by the pool a line names, else by its kind)."""
    if run.ledger is None or not isinstance(run.ledger.get("pools"), dict):
        out.append("ledger.json: missing or not a ledger; a finished run always leaves it")
        return
    got = written(run.results, run.ledger,
                  first_line_at(results_path, results_from(run.ledger)))
    if not got.compared:  # old lines and a ledger from before pools said their kinds
        return
    name = run.results.name
    since = f" from line {got.first_line} (this start's)" if got.first_line > 1 else ""
    pools = {k: p for k, p in run.ledger["pools"].items() if isinstance(p, dict)}
    for pool, p in sorted(pools.items()):
        have = len(got.pools.get(pool, ()))
        if p.get("processed") != have:
            of = "/".join(sorted(got.kinds.get(pool) or p.get("kinds") or [])) or "no kind"
            out.append(f"ledger.json pool {pool}: processed {p.get('processed')}, {name} has "
                       f"{have} distinct seqs of {of}{since}")
    for what, seqs in sorted(got.unclaimed.items()):
        makers = sorted(k for k, p in pools.items() if what in (p.get("kinds") or []))
        why = ("which ledger.json does not have" if what.startswith("pool ") else
               f"which name no pool, and pools {', '.join(makers)} all make {what}"
               if makers else "which no pool of ledger.json made")
        out.append(f"{name}{since}: {len(seqs)} seqs of {what}, {why}")


def _tracks(run: _Run, out: list[str]) -> None:
    """Every track id on a line is a track of tracks.jsonl, of the lines' label and span."""
    lines: dict[int, list[tuple[int, int, float, str, int]]] = {}
    for item in run.tracked:
        lines.setdefault(item[4], []).append(item)
    name, tname = run.results.name, run.tracks.name
    for tid, of in sorted(lines.items()):
        if tid not in run.by_id:
            out.append(f"{name} line {of[0][0]}: track {tid} ({len(of)} lines) is not in "
                       f"{tname}")
            continue
        n, t = run.by_id[tid]
        label = t.label
        said = Counter(lb for _n, _s, _t, lb, _i in of)
        unseen = max(0, t.pairs - len(of))  # boxes before its id
        top, most = said.most_common(1)[0]
        if top != label and most > said.get(label, 0) + unseen:
            out.append(f"{tname} line {n}: track {tid} is {label}, but {said.get(label, 0)} "
                       f"of its {len(of)} lines in {name} say {label} and {most} say {top}")
        tol = TIME_TOL_S + SLEW * (t.last_s - t.first_s)
        outside = [x for x in of if not t.first_s - tol <= x[2] <= t.last_s + tol]
        if outside:
            x = outside[0]
            out.append(f"{name} line {x[0]}: track {tid} at {x[2]:.3f}, outside its span "
                       f"{t.first_s:.3f}-{t.last_s:.3f} in {tname} line {n}"
                       f"{f' ({len(outside)} lines)' if len(outside) > 1 else ''}")


def _interval(starts: list[tuple[float, float, int]], t: float) -> int | None:
    """The index of the interval (start, end, line) that holds capture time t."""
    found = None
    for i, (start, end, _n) in enumerate(starts):
        if start - TIME_TOL_S / 2 <= t <= end + TIME_TOL_S / 2:
            found = i  # the later one on a shared boundary: intervals start there
    return found


def _counts(run: _Run, out: list[str]) -> None:
    """Visits and MaxN per interval and label against the tracks and their lines."""
    spans = sorted((c.start_s, c.end_s, n) for n, c in run.counts.items)
    labels = {tid: t.label for tid, (_n, t) in run.by_id.items()}
    first: dict[int, float] = {}  # track -> the first time a line carries its id
    # A pair is its seq and capture time: a run directory started again numbers its pairs
    # from 0 again, so one seq may be two pairs of results.jsonl.
    at: dict[tuple[int, float], set[int]] = {}  # pair -> the tracks on its lines
    for _n, seq, t, _lb, tid in run.tracked:
        first[tid] = min(first.get(tid, t), t)
        at.setdefault((seq, t), set()).add(tid)
    visits: Counter[tuple[int, str]] = Counter()
    for tid, (n, track) in sorted(run.by_id.items()):
        seen = first.get(tid, track.first_s)
        i = _interval(spans, seen)
        if i is None:
            out.append(f"{run.tracks.name} line {n}: track {tid} first seen at {seen:.3f}, "
                       f"in no interval of {run.counts.name}")
        else:
            visits[(i, labels[tid])] += 1
    max_n: dict[tuple[int, str], int] = {}
    for (_seq, t), tids in at.items():
        i = _interval(spans, t)
        if i is None:
            continue
        for lb, k in Counter(labels[x] for x in tids if x in labels).items():
            max_n[(i, lb)] = max(max_n.get((i, lb), 0), k)
    written = {n: c for n, c in run.counts.items}
    for i, (start, _end, n) in enumerate(spans):
        rows = {r.label: (r.visits, r.max_n) for r in written[n].labels}
        implied = {lb for (j, lb) in (*visits, *max_n) if j == i}
        for lb in sorted(set(rows) | implied):
            row = rows.get(lb, (0, 0))
            for key, have, want in (("visits", row[0], visits.get((i, lb), 0)),
                                    ("max_n", row[1], max_n.get((i, lb), 0))):
                if have != want:
                    out.append(f"{run.counts.name} line {n} ({_secs(start)}): {lb} {key} "
                               f"{have}, the tracks imply {want}")


def _surface(run: _Run, path: Path, out: list[str]) -> None:
    """Each record the surface wrote matches a line the box wrote."""
    got = read_jsonl(path)
    name = f"surface {path.name}"
    if not got.exists:
        out.append(f"{name}: missing")
        return
    out += [f"{name} line {n}: not a record" for n in got.bad]
    if got.cut is not None:
        out.append(f"{name} line {got.cut}: cut mid-way")
    results: dict[tuple[str, int], list[ResultItem]] = {}
    for _n, (kind, item) in run.results.items:
        results.setdefault((kind, item.seq), []).append(item)
    counts = {_secs(c.start_s): c for _n, c in run.counts.items}
    labels = {t.label for _n, t in run.by_id.values()}
    def result(n: int, kind: str, body: dict[str, Any], within: str = "") -> None:
        # The surface's record is the modem's (link_record), its keys compared to the line's.
        mine = results.get((kind, body.get("seq", -1)), [])
        keys = [k for k in ("timestamp", "label", "track") if k in body]
        if not any(all(getattr(b, k, UNSET) == body[k] for k in keys) for b in mine):
            out.append(f"{name} line {n}: {within}{kind} seq {body.get('seq')} "
                       f"({', '.join(f'{k} {body[k]}' for k in keys)}) is no line of "
                       f"{run.results.name}")

    for n, obj in got.items:
        (kind, body), = obj.items()
        if not isinstance(body, dict):
            out.append(f"{name} line {n}: {kind} is not a record")
        elif kind in run.seqs:
            result(n, kind, body)
        elif kind == "aggregate":  # its best records, whole or their core, are lines too
            for rec in body.get("best") or []:
                for bkind, bbody in (rec.items() if isinstance(rec, dict) else ()):
                    if bkind in run.seqs and isinstance(bbody, dict):
                        result(n, bkind, bbody, "an aggregate's best ")
        elif kind == "track":
            had = run.by_id.get(body.get("id", -1))
            box = (had[1].label, _secs(had[1].first_s)) if had else (None, None)
            if box != (body.get("label"), body.get("start")):
                out.append(f"{name} line {n}: track {body.get('id')} {body.get('label')} from "
                           f"{body.get('start')}, {run.tracks.name} has "
                           f"{'no such track' if not had else f'{box[0]} from {box[1]}'}")
        elif kind == "counts":
            c = counts.get(body.get("start", ""))
            sent = {r.get("label"): (r.get("visits"), r.get("max_n"))
                    for r in body.get("labels") or []}
            if c is None or c.pairs != body.get("pairs") or sent != {
                    r.label: (r.visits, r.max_n) for r in c.labels}:
                out.append(f"{name} line {n}: counts from {body.get('start')} (pairs "
                           f"{body.get('pairs')}) differ from {run.counts.name}'s "
                           f"{'none' if c is None else c.pairs}")
        elif kind in ("new_label", "new_max_n") and body.get("label") not in labels:
            out.append(f"{name} line {n}: {kind} {body.get('label')}, a label no track of "
                       f"{run.tracks.name} has")
        elif kind == "undecodable":
            out.append(f"{name} line {n}: message {body.get('id')} did not decode")


def check_run(run_dir: Path, *, results_file: str = "results.jsonl",
              tracks_file: str = "tracks.jsonl", counts_file: str = "counts.jsonl",
              surface: Path | None = None) -> list[str]:
    """Every disagreement between a finished run's files, one line each; empty when they
    tell one story. A run without tracking (no tracks.jsonl) is checked for the rest."""
    out: list[str] = []
    run = _load(run_dir, results_file, tracks_file, counts_file, out)
    _ledger(run, run_dir / results_file, out)
    if run.tracks.exists or run.tracked:
        _tracks(run, out)
    if run.counts.exists:
        _counts(run, out)
    if surface is not None:
        _surface(run, surface, out)
    return out
