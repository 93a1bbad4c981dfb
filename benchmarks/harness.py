"""The benchmarks' one harness: common options, repeats summarised as a median with its
spread, CPU seconds of a process tree, one result type, and its JSON and markdown.

Pure functions where a decision is made (summarise, the rendering, the JSON mapping); the
shells (timing a callable, reading /proc through psutil, writing files) are thin."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import psutil

DEFAULT_OUT = Path("bench-results")
Spread = Literal["minmax", "iqr"]

# --- options ------------------------------------------------------------------------------


def options(doc: str | None, *, repeats: int = 5, quick_help: str = "short windows",
            ) -> argparse.ArgumentParser:
    """The options every benchmark takes (--quick, --repeats N, --out DIR); a bench adds its
    own to the parser it gets back. The module's docstring is the help text."""
    ap = argparse.ArgumentParser(prog=_prog(sys.argv[0]), description=doc,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help=quick_help)
    ap.add_argument("--repeats", type=int, default=repeats,
                    help=f"repeats of each measurement, median kept (default {repeats})")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT,
                    help=f"folder for NAME.json and NAME.md (default {DEFAULT_OUT})")
    return ap


def _prog(argv0: str) -> str | None:
    """How the help names a bench: `python -m benchmarks.NAME` for a module of this package."""
    path = Path(argv0)
    return f"python -m benchmarks.{path.stem}" if path.parent.name == "benchmarks" else None


# --- repeats ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Summary:
    """Repeated samples as their median and spread: [low, high] is the range (minmax) or
    the interquartile range (iqr, inclusive quartiles)."""

    median: float
    low: float
    high: float
    n: int
    spread: Spread = "minmax"


def summarise(samples: Sequence[float], spread: Spread = "minmax") -> Summary:
    """Median and spread of samples (pure). IQR needs two samples; one is its own spread."""
    if not samples:
        raise ValueError("no samples to summarise")
    xs = sorted(float(x) for x in samples)
    med = statistics.median(xs)
    if spread == "minmax" or len(xs) < 2:
        return Summary(med, xs[0], xs[-1], len(xs), spread)
    q1, _, q3 = statistics.quantiles(xs, n=4, method="inclusive")
    return Summary(med, q1, q3, len(xs), spread)


def repeat(fn: Callable[[], float], repeats: int) -> list[float]:
    """The figure fn returns, measured `repeats` times (interleave paths in fn's caller when
    they are to be compared: a shared machine's noise then hits each alike)."""
    return [float(fn()) for _ in range(max(1, repeats))]


def per_call(fn: Callable[[], Any], calls: int,
             clock: Callable[[], float] = time.process_time) -> float:
    """Seconds of `clock` per call of fn over `calls` calls (one warm-up call first)."""
    fn()
    t0 = clock()
    for _ in range(calls):
        fn()
    return (clock() - t0) / max(1, calls)


# --- CPU of a process tree ----------------------------------------------------------------


def pace(t0: float, n: int, rate: float | None) -> None:
    """Sleep until the n-th send of a source paced at `rate` per second from monotonic t0
    is due (at once when `rate` is None or 0: as fast as it goes)."""
    if rate:
        wait = t0 + n / rate - time.monotonic()
        if wait > 0:
            time.sleep(wait)


def tree_cpu(pid: int, *, children: bool = True) -> float:
    """User + system CPU seconds of process pid and its descendants, living and reaped.

    Sampled once at the start of a window and once at its end, the difference is what the
    tree spent in between: a child that ends inside the window moves from its own entry to
    its parent's reaped-children times, so it is still counted (a child started before the
    window and reaped inside it counts whole: join the last window's children first). With
    children=False, the process's own CPU only (a row per process of a tree whose other
    processes have rows of their own). A process gone before the sample counts 0."""
    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)] if children else [root]
    except psutil.Error:
        return 0.0
    total = 0.0
    for p in procs:
        with contextlib.suppress(psutil.Error):
            t = p.cpu_times()
            total += t.user + t.system
            if children:
                total += t.children_user + t.children_system
    return total


# --- the result ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Figure:
    """One measured figure: value in unit, with its spread [low, high] when repeated."""

    value: float | int | str | None
    unit: str = ""
    low: float | None = None
    high: float | None = None
    digits: int = 2


def figure(s: Summary, unit: str = "", scale: float = 1.0, digits: int = 2) -> Figure:
    """A summary as a figure, its values times scale (seconds to ms: 1000); one sample has
    no spread to show."""
    if s.n < 2:
        return Figure(round(s.median * scale, digits + 2), unit, digits=digits)
    return Figure(round(s.median * scale, digits + 2), unit, round(s.low * scale, digits + 2),
                  round(s.high * scale, digits + 2), digits)


@dataclass
class Row:
    """One line of a table: its label and its figures by name (column)."""

    label: str
    figures: dict[str, Figure]


@dataclass
class Result:
    """What one benchmark (or one of its tables) measured: rows of named figures, notes in
    words below the table, and `data`, the bench's own detail kept in the JSON only."""

    bench: str
    title: str = ""
    key: str = ""  # the heading of the label column
    rows: list[Row] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    data: dict[str, Any] = field(default_factory=dict)

    def add(self, label: str, **figures: Figure) -> Row:
        row = Row(label, dict(figures))
        self.rows.append(row)
        return row


def to_json(results: Sequence[Result]) -> dict[str, Any]:
    """Results as one JSON object (pure)."""
    return {"results": [asdict(r) for r in results]}


def from_json(obj: dict[str, Any]) -> list[Result]:
    """The inverse of to_json (pure)."""
    out = []
    for r in obj["results"]:
        rows = [Row(row["label"], {k: Figure(**f) for k, f in row["figures"].items()})
                for row in r["rows"]]
        out.append(Result(r["bench"], r["title"], r["key"], rows, list(r["notes"]),
                          dict(r["data"])))
    return out


# --- markdown -----------------------------------------------------------------------------


def cell(f: Figure | None) -> str:
    """One figure as a table cell: '12.30 [11.00-13.50]', a string as it is, '' for none."""
    if f is None or f.value is None:
        return ""
    if isinstance(f.value, str):
        return f.value
    text = _num(f.value, f.digits)
    if f.low is not None and f.high is not None:
        text += f" [{_num(f.low, f.digits)}-{_num(f.high, f.digits)}]"
    return text


def _right(f: Figure | None) -> bool:
    """A cell aligned right: a number, or text that does not start with a letter ('-',
    '**12.0**', '2.0 (0.7) / 10')."""
    return f is None or not isinstance(f.value, str) or not f.value[:1].isalpha()


def _num(x: float, digits: int) -> str:
    return f"{x:,.{digits}f}" if isinstance(x, float) else f"{x:,}"


def columns(rows: Iterable[Row]) -> list[tuple[str, str]]:
    """(name, unit) of every column, in the order first seen (pure). A column holds one unit:
    figures of one name in two units are refused (the heading would misstate one)."""
    seen: dict[str, str] = {}
    for row in rows:
        for name, f in row.figures.items():
            if f.value is not None and seen.setdefault(name, f.unit) != f.unit:
                raise ValueError(f"column {name!r} in {seen[name]!r} and {f.unit!r}")
    return list(seen.items())


def table(rows: Sequence[Row], key: str = "") -> str:
    """Rows as one markdown table: a column per figure name, its unit in the heading, text
    left-aligned and numbers right-aligned (pure)."""
    cols = columns(rows)
    if not cols and not rows:
        return ""
    heads = [f"{n} ({u})" if u else n for n, u in cols]
    numeric = [all(_right(r.figures.get(n)) for r in rows) for n, _ in cols]
    lines = ["| " + " | ".join([key, *heads]) + " |",
             "|---|" + "".join("---:|" if num else "---|" for num in numeric)]
    for r in rows:
        lines.append("| " + " | ".join([r.label, *(cell(r.figures.get(n)) for n, _ in cols)])
                     + " |")
    return "\n".join(lines)


def markdown(results: Sequence[Result]) -> str:
    """Results as markdown: per result its title, its table and its notes (pure)."""
    parts = []
    for r in results:
        block = [f"## {r.title}" if r.title else "", table(r.rows, r.key), *r.notes]
        parts.append("\n\n".join(b for b in block if b))
    return "\n\n".join(parts) + "\n"


# --- the shell ----------------------------------------------------------------------------


def write(out: Path, name: str, results: Sequence[Result]) -> tuple[Path, Path]:
    """out/NAME.json and out/NAME.md, the folder made when missing; their paths."""
    out.mkdir(parents=True, exist_ok=True)
    js, md = out / f"{name}.json", out / f"{name}.md"
    js.write_text(json.dumps(to_json(results), indent=1) + "\n")
    md.write_text(markdown(results))
    return js, md


def read(path: Path) -> list[Result]:
    """Results from a NAME.json that write() made."""
    return from_json(json.loads(path.read_text()))


def machine() -> dict[str, Any]:
    """What the figures were measured on: cores, Python, load average now."""
    return {"cores": os.cpu_count(), "python": sys.version.split()[0],
            "load": [round(x, 2) for x in os.getloadavg()]}


def log(bench: str, text: str) -> None:
    """Progress on stderr (stdout is the bench's report)."""
    print(f"[{bench}] {text}", file=sys.stderr, flush=True)
