"""`trapflow check RUN_DIR --against OTHER`: whether a re-analysis of a run's pairs (a
`trapflow replay` run directory, a `trapflow process` output) tells the live run's story.
Pure but for reading the two results files.

A re-analysis numbers its pairs from 0 (its seq is the recording's order, not the live
run's), so the two are joined by what both carry exactly: the pair's capture time, the
`timestamp` of every line (issue 32: the recording stamps each pair with the live run's
capture time, and replay and process label its results with it).

What must agree, one disagreement line each:

- the re-analysis's pairs are the live run's: of its result lines whose time lies within
  the live run's span, at least MIN_SHARE carry the capture time of a pair the live run
  wrote a line for (a pair the live run dropped in every pool has no line to match, hence
  a share, not all);
- a kind both made, on the pairs both analysed with the same model (`model`, the weights'
  hash), gives the same labels (as a multiset per pair: boxes may move by a pixel, the live
  pair was raw where the recording holds JPEG, but a crab stays a crab) on at least
  MIN_SHARE of them.

What is only said (the summary): per kind, the pairs both analysed, and those only one
did (a live run drops pairs under load or behind its motion gate; a re-analysis at
`--rate 0` analyses every pair of its recording, which starts and ends where the recorder
did).
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from trapflow.export.run_files import label_s, read_results
from trapflow.wire.result_lines import MonoIRLine, ResultLine, StereoIRLine

MIN_SHARE = 0.99
"""The share of joined lines and labels that must agree (the issue's 99 %)."""


@dataclass
class _Side:
    """One run's lines by kind and capture time: the labels and models of each pair."""

    times: set[str] = field(default_factory=set)  # every line's capture time
    span: tuple[float, float] | None = None
    labels: dict[str, dict[str, Counter[str]]] = field(
        default_factory=lambda: defaultdict(lambda: defaultdict(Counter)))
    models: dict[str, dict[str, str]] = field(default_factory=lambda: defaultdict(dict))
    lines: dict[str, int] = field(default_factory=Counter)


def _side(lines: list[ResultLine]) -> _Side:
    side = _Side()
    secs: list[float] = []
    for line in lines:
        item, kind = line.item, line.kind
        side.times.add(item.timestamp)
        side.lines[kind] += 1
        if (t := label_s(item.timestamp)) is not None:
            secs.append(t)
        by_pair = side.labels[kind][item.timestamp]
        if isinstance(item, (MonoIRLine, StereoIRLine)):
            by_pair[item.label] += 1
            if isinstance(item.model, str):
                side.models[kind][item.timestamp] = item.model
    if secs:
        side.span = (min(secs), max(secs))
    return side


def results_path(where: Path) -> Path:
    """A results file given as itself or as the folder holding results.jsonl."""
    return where / "results.jsonl" if where.is_dir() else where


def compare(live_lines: list[ResultLine], other_lines: list[ResultLine], live_name: str,
            other_name: str) -> tuple[list[str], list[str]]:
    """(disagreements, summary lines) of a re-analysis against its live run."""
    live, other = _side(live_lines), _side(other_lines)
    problems: list[str] = []
    summary: list[str] = []
    if live.span is None or other.span is None:
        return [f"{other_name if other.span is None else live_name}: no result line to "
                "compare"], summary
    lo, hi = live.span
    inside = [t for t in other.times if (s := label_s(t)) is not None and lo <= s <= hi]
    joined = [t for t in inside if t in live.times]
    summary.append(f"pairs: {len(joined)} of the {len(inside)} pairs {other_name} analysed "
                   f"within the live run's span carry a live capture time")
    if not inside:
        problems.append(f"{other_name}: no pair within the live run's span "
                        f"({live_name}): not a re-analysis of its pairs")
    elif len(joined) < MIN_SHARE * len(inside):
        problems.append(f"{other_name}: {len(inside) - len(joined)} of {len(inside)} pairs "
                        f"within the live run's span carry no capture time of {live_name} "
                        f"(at least {MIN_SHARE:.0%} must)")
    for kind in sorted(set(live.labels) & set(other.labels)):
        _kind(kind, live, other, other_name, problems, summary)
    for kind in sorted(set(live.labels) ^ set(other.labels)):
        only = live_name if kind in live.labels else other_name
        summary.append(f"{kind}: only in {only}")
    return problems, summary


def _kind(kind: str, live: _Side, other: _Side, other_name: str, problems: list[str],
          summary: list[str]) -> None:
    a, b = live.labels[kind], other.labels[kind]
    both = set(a) & set(b)
    summary.append(f"{kind}: {len(both)} pairs in both, {len(set(a) - set(b))} only live, "
                   f"{len(set(b) - set(a))} only in {other_name}")
    same_model = [t for t in both if (m := live.models[kind].get(t)) is not None
                  and m == other.models[kind].get(t)]
    if not same_model:
        return
    agree = [t for t in same_model if a[t] == b[t]]
    summary.append(f"{kind}: labels agree on {len(agree)} of {len(same_model)} pairs "
                   "analysed with the same model")
    if len(agree) < MIN_SHARE * len(same_model):
        t = next(t for t in sorted(same_model) if a[t] != b[t])
        problems.append(f"{kind}: labels differ on {len(same_model) - len(agree)} of "
                        f"{len(same_model)} pairs analysed with the same model (first at "
                        f"{t}: live {dict(a[t])}, {other_name} {dict(b[t])})")


def check_against(live: Path, other: Path) -> tuple[list[str], list[str]]:
    """Read both results files and compare them (paths to the files)."""
    lines = []
    bad: list[str] = []
    for path in (live, other):
        jsonl = read_results(path)
        if not jsonl.exists:
            return [f"{path}: no such results file"], []
        lines.append(jsonl.bodies())
        if path == other and jsonl.bad:  # the live run's are check_run's to say
            first = jsonl.bad[0]
            bad.append(f"{path}: {len(jsonl.bad)} lines are not result lines (line {first}: "
                       f"{jsonl.why.get(first, 'not a result line')})")
    problems, summary = compare(lines[0], lines[1], str(live), str(other))
    return bad + problems, summary
