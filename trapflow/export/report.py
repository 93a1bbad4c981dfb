"""`trapflow report RUN_DIR`: one self-contained HTML page of a run, charts as inline SVG.

Reads what a run leaves in its directory (results.jsonl, counts.jsonl, tracks.jsonl,
ledger.json, trapflow.log, the event folders' event.json) into a RunSummary (summarize, pure
but for reading those files), then renders it (render_html, pure): detections per class per
hour, visits and MaxN per label per hour, the length-frequency of each label's tracks, the VO
path seen from above, result rates per pool over time, drops and losses from the ledger,
restarts and events. No JavaScript, no external file, no network: the page opens on a laptop
at the dock.
"""

from __future__ import annotations

import datetime as dt
import html
import json
import logging
import math
import re
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from trapflow.errors import TrapflowError
from trapflow.wire.pool_counters import LEDGER_STATES

log = logging.getLogger(__name__)

TIME_FORMAT = "%Y-%m-%d %H:%M:%S.%f"
RATE_BIN_S = 10  # seconds per point of the result-rate chart
MIN_LAST_BIN_S = 2.0  # a last, partial rate bin shorter than this is left out
_RESTART = re.compile(r"^(\S+ \S+) .*restarting (\S+) \(restart (\d+)\)")


class ReportError(TrapflowError):
    """A run directory cannot be reported on (missing, no results)."""


@dataclass
class RunSummary:
    """What a run did, ready to draw."""

    run: str
    first: str = ""  # UTC timestamps of the first and last result
    last: str = ""
    lines: int = 0
    per_class_hour: dict[str, dict[str, int]] = field(default_factory=dict)  # hour -> label -> n
    vo_path: list[tuple[float, float]] = field(default_factory=list)  # (x, z) of each ok pose
    vo_ok: int = 0
    vo_total: int = 0
    rates: dict[str, list[tuple[float, float]]] = field(default_factory=dict)  # pool -> (s, /s)
    ledger: dict[str, Any] = field(default_factory=dict)
    restarts: list[tuple[str, str, int]] = field(default_factory=list)  # (time, node, count)
    events: list[dict[str, Any]] = field(default_factory=list)  # event.json + name
    # hour -> label -> [visits, MaxN, dwell s] (counts.jsonl, by the interval's start)
    counts_hour: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    lengths: dict[str, list[float]] = field(default_factory=dict)  # label -> tracks' length_m
    meta: dict[str, Any] = field(default_factory=dict)  # run.json: config, versions, rig
    ranges: dict[str, list[float]] = field(default_factory=dict)  # label -> tracks' range_m
    speeds: dict[str, list[float]] = field(default_factory=dict)  # label -> tracks' speed_m_s


def _time(label: str) -> dt.datetime:
    return dt.datetime.strptime(label, TIME_FORMAT)


def _jsonl(path: Path, kind: str) -> list[dict[str, Any]]:
    """The bodies of one kind of line of a JSON-lines file (none when it is absent)."""
    out = []
    if path.is_file():
        for n, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            try:
                body = json.loads(raw).get(kind)
            except (ValueError, AttributeError):
                body = None
            if isinstance(body, dict):
                out.append(body)
            else:
                log.warning("report: %s line %d is no %s line; skipped", path, n, kind)
    return out


def observations(s: RunSummary, counts: list[dict[str, Any]],
                 tracks: list[dict[str, Any]]) -> None:
    """Visits, MaxN and dwell per label per hour (an interval counts in the hour it starts;
    MaxN of an hour is the largest of its intervals'), and each label's track lengths,
    ranges at first sighting and speeds."""
    for c in counts:
        try:
            hour = dt.datetime.fromtimestamp(float(c["start_s"]), dt.timezone.utc)
            per = s.counts_hour.setdefault(hour.strftime("%Y-%m-%d %H:00"), {})
            for lb in c["labels"]:
                v = per.setdefault(str(lb["label"]), [0, 0, 0.0])
                v[0] += int(lb["visits"])
                v[1] = max(v[1], int(lb["max_n"]))
                v[2] += float(lb["dwell_s"])
        except (KeyError, TypeError, ValueError):
            log.warning("report: a counts line without start_s and labels; skipped")
    for t in tracks:
        for key, into in (("length_m", s.lengths), ("range_m", s.ranges),
                          ("speed_m_s", s.speeds)):
            got = t.get(key)
            if isinstance(got, (int, float)) and (got > 0 or got == 0 and key == "speed_m_s"):
                into.setdefault(str(t.get("label", "")), []).append(float(got))


def summarize(run_dir: Path, events_folder: str = "events", counts_file: str = "counts.jsonl",
              tracks_file: str = "tracks.jsonl") -> RunSummary:
    """Read a run directory; ReportError when it has no results.jsonl."""
    results = run_dir / "results.jsonl"
    if not results.is_file():
        raise ReportError(f"report: expected {results} (a run directory with results), found "
                          "none; name the directory a pipeline ran in (its --run-dir)")
    s = RunSummary(run=run_dir.name)
    seqs: dict[str, set[int]] = {}
    t0: dt.datetime | None = None
    times: dict[str, list[float]] = {}
    with results.open(encoding="utf-8") as fh:
        for n, raw in enumerate(fh, 1):
            try:
                (algo, body), = json.loads(raw).items()
                t = _time(body["timestamp"])
            except (ValueError, KeyError, TypeError, AttributeError):
                log.warning("report: %s line %d is no result line; skipped", results, n)
                continue
            s.lines += 1
            s.first = s.first or body["timestamp"]
            s.last = body["timestamp"]
            t0 = t0 or t
            label = body.get("label")
            if algo == "mono_ir" and label and label != "none":
                hour = t.strftime("%Y-%m-%d %H:00")
                per = s.per_class_hour.setdefault(hour, {})
                per[label] = per.get(label, 0) + 1
            if algo == "stereo_vo":
                s.vo_total += 1
                pose = body.get("pose")
                if body.get("ok") and isinstance(pose, list) and len(pose) == 3:
                    s.vo_ok += 1
                    s.vo_path.append((float(pose[0][3]), float(pose[2][3])))
            seq = body.get("seq")
            if isinstance(seq, int) and seq not in seqs.setdefault(algo, set()):
                seqs[algo].add(seq)  # a pair processed: one per pair, not one per detection
                times.setdefault(algo, []).append((t - t0).total_seconds())
    end = max((ts[-1] for ts in times.values()), default=0.0)
    s.rates = {algo: rate_bins(ts, end) for algo, ts in times.items()}
    ledger = run_dir / "ledger.json"
    if ledger.is_file():
        s.ledger = json.loads(ledger.read_text(encoding="utf-8"))
    meta = run_dir / "run.json"
    if meta.is_file():
        s.meta = json.loads(meta.read_text(encoding="utf-8"))
    logfile = run_dir / "trapflow.log"
    if logfile.is_file():
        for line in logfile.read_text(encoding="utf-8", errors="replace").splitlines():
            m = _RESTART.match(line)
            if m:
                s.restarts.append((m.group(1), m.group(2), int(m.group(3))))
    observations(s, _jsonl(run_dir / counts_file, "counts"),
                 _jsonl(run_dir / tracks_file, "track"))
    for info in sorted((run_dir / events_folder).glob("*/event.json")):
        try:
            s.events.append({"name": info.parent.name, **json.loads(info.read_text())})
        except ValueError:
            log.warning("report: %s is not JSON; skipped", info)
    return s


def rate_bins(times: list[float], end: float, width: float = RATE_BIN_S
              ) -> list[tuple[float, float]]:
    """Pairs per second in bins of `width` s from 0 (seconds since the first result) to the
    run's last result at `end`, each at its bin's start. The last bin is cut short by the
    run's end: its count is divided by the time it really covers (its start to `end`), not
    by the whole width, so the rate does not dive there; covering less than MIN_LAST_BIN_S
    it is dropped (too few pairs for a rate), unless it is the only one."""
    if not times:
        return []
    counts: dict[int, int] = {}
    for t in times:
        counts[int(t // width)] = counts.get(int(t // width), 0) + 1
    last = int(end // width)
    out = [(b * width, counts.get(b, 0) / width) for b in range(last)]
    covered = end - last * width
    if covered >= MIN_LAST_BIN_S or not out:
        out.append((last * width, counts.get(last, 0) / max(covered, MIN_LAST_BIN_S)))
    return out


# --- rendering ---------------------------------------------------------------------------

W, H, PAD = 640, 240, 40
# The frame every chart draws in (_axes): PLOT_W x PLOT_H pixels, its lower edge at PLOT_BOTTOM.
PLOT_W, PLOT_H, PLOT_BOTTOM = W - 2 * PAD, H - 2 * PAD, H - PAD - PAD // 2


def equal_extent(x0: float, x1: float, y0: float, y1: float, aspect: float
                 ) -> tuple[float, float, float, float]:
    """The data ranges around (x0..x1, y0..y1), centred, widened so that x span / y span is
    the frame's aspect (width / height in pixels): a metre is as long along x as along y."""
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    half_y = max((x1 - x0) / aspect, y1 - y0, 1e-6) / 2
    half_x = half_y * aspect
    return cx - half_x, cx + half_x, cy - half_y, cy + half_y
COLOURS = ("#d95f02", "#1b9e77", "#7570b3", "#e7298a", "#66a61e", "#e6ab02")


def _scale(lo: float, hi: float, a: float, b: float) -> Any:
    span = (hi - lo) or 1.0
    return lambda v: a + (v - lo) / span * (b - a)


def _axes(title: str, xlabel: str, ylabel: str) -> list[str]:
    e = html.escape
    return [f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" '
            f'viewBox="0 0 {W} {H}" role="img" aria-label="{e(title)}">',
            f'<rect x="{PAD}" y="{PAD // 2}" width="{W - 2 * PAD}" height="{H - 2 * PAD}" '
            'fill="none" stroke="#999"/>',
            f'<text x="{W // 2}" y="{H - 6}" text-anchor="middle" font-size="12">'
            f'{e(xlabel)}</text>',
            f'<text x="12" y="{H // 2}" font-size="12" transform="rotate(-90 12 {H // 2})" '
            f'text-anchor="middle">{e(ylabel)}</text>']


def svg_lines(title: str, series: dict[str, list[tuple[float, float]]], xlabel: str,
              ylabel: str, equal: bool = False) -> str:
    """A line chart of named (x, y) series, with its value range written on the axes."""
    pts = [p for s in series.values() for p in s]
    if not pts:
        return f"<p>{html.escape(title)}: no data.</p>"
    xs, ys = [p[0] for p in pts], [p[1] for p in pts]
    x0, x1, y0, y1 = min(xs), max(xs), min(ys), max(ys)
    if equal:  # a path seen from above: one metre as many pixels both ways (issue 22)
        x0, x1, y0, y1 = equal_extent(x0, x1, y0, y1, PLOT_W / PLOT_H)
    sx = _scale(x0, x1, PAD, W - PAD)
    sy = _scale(y0, y1, PLOT_BOTTOM, PAD // 2)
    out = _axes(title, xlabel, ylabel)
    out.append(f'<text x="{PAD}" y="{H - PAD + 14}" font-size="10">{x0:.3g}</text>'
               f'<text x="{W - PAD}" y="{H - PAD + 14}" font-size="10" text-anchor="end">'
               f'{x1:.3g}</text><text x="{PAD - 4}" y="{H - PAD}" font-size="10" '
               f'text-anchor="end">{y0:.3g}</text><text x="{PAD - 4}" y="{PAD // 2 + 10}" '
               f'font-size="10" text-anchor="end">{y1:.3g}</text>')
    for i, (name, s) in enumerate(sorted(series.items())):
        colour = COLOURS[i % len(COLOURS)]
        d = " ".join(f"{sx(x):.1f},{sy(y):.1f}" for x, y in s)
        out.append(f'<polyline class="series" data-name="{html.escape(name)}" '
                   f'data-points="{len(s)}" fill="none" stroke="{colour}" '
                   f'stroke-width="1.5" points="{d}"/>')
        out.append(f'<text x="{W - PAD - 4}" y="{PAD // 2 + 14 + 14 * i}" font-size="11" '
                   f'text-anchor="end" fill="{colour}">{html.escape(name)}</text>')
    out.append("</svg>")
    return "".join(out)


# Bin widths of a length-frequency histogram (metres): the narrowest giving at most MAX_BINS.
BIN_WIDTHS_M = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)
MAX_BINS = 15


def _bin(v: float, width: float) -> int:
    return math.floor(v / width + 1e-9)  # 0.3 / 0.05 is 5.999999999999999


def histogram(values: list[float]) -> tuple[float, int, list[int]]:
    """Bin width, index of the first bin and counts of values (not empty) in bins aligned to
    multiples of the width, the narrowest width giving at most MAX_BINS bins."""
    lo, hi = min(values), max(values)
    width = next((w for w in BIN_WIDTHS_M if _bin(hi, w) - _bin(lo, w) < MAX_BINS),
                 BIN_WIDTHS_M[-1])
    first = _bin(lo, width)
    counts = [0] * (_bin(hi, width) - first + 1)
    for v in values:
        counts[_bin(v, width) - first] += 1
    return width, first, counts


def svg_bars(label: str, values: list[float]) -> str:
    """A length-frequency histogram of one label (bars carry their bin and count)."""
    width, first, counts = histogram(values)
    e = html.escape
    top = max(counts)
    bar_w = (W - 2 * PAD) / len(counts)
    bottom = PLOT_BOTTOM
    sy = _scale(0, top, bottom, PAD // 2)
    out = _axes(f"length-frequency of {label}", f"length (m), {width:g} m bins",
                "tracks")
    for i, n in enumerate(counts):
        lo, hi = (first + i) * width, (first + i + 1) * width
        out.append(f'<rect class="bar" data-label="{e(label)}" data-from="{lo:.3f}" '
                   f'data-to="{hi:.3f}" data-count="{n}" x="{PAD + i * bar_w + 1:.1f}" '
                   f'y="{sy(n):.1f}" width="{bar_w - 2:.1f}" height="{bottom - sy(n):.1f}" '
                   f'fill="{COLOURS[0]}"><title>{lo:.3f}-{hi:.3f} m: {n}</title></rect>')
    out.append(f'<text x="{PAD}" y="{H - PAD + 14}" font-size="10">{first * width:.3g}</text>'
               f'<text x="{W - PAD}" y="{H - PAD + 14}" font-size="10" text-anchor="end">'
               f'{(first + len(counts)) * width:.3g}</text><text x="{PAD - 4}" '
               f'y="{PAD // 2 + 10}" font-size="10" text-anchor="end">{top}</text></svg>')
    return "".join(out)


def _lengths(s: RunSummary) -> list[str]:
    def median(values: list[float] | None, digits: int) -> str:
        return f"{statistics.median(values):.{digits}f}" if values else "-"

    rows = [[lb, len(v), f"{statistics.median(v):.3f}", f"{min(v):.3f}", f"{max(v):.3f}",
             median(s.ranges.get(lb), 2), median(s.speeds.get(lb), 3)]
            for lb, v in sorted(s.lengths.items())]
    return [_table(["label", "tracks measured", "median (m)", "min (m)", "max (m)",
                    "median range (m)", "median speed (m/s)"], rows),
            *(svg_bars(lb, v) for lb, v in sorted(s.lengths.items()))]


def _run_table(meta: dict[str, Any]) -> str:
    """run.json as rows: when and how long, the config, the rig, the versions."""
    if not meta:
        return "<p>no run.json (a run of an older trapflow, or one that did not end)</p>"
    cfg, rig = meta.get("config", {}), meta.get("rig") or {}
    src = cfg.get("source", {})
    pools = ", ".join(f"{n} x{p.get('count')} {p.get('plugin')} ({p.get('policy')})"
                      for n, p in sorted(cfg.get("pools", {}).items()))
    vers = ", ".join(f"{k} {v}" for k, v in meta.get("versions", {}).items() if v)
    return _table(["run", "as run.json has it"], [
        ["ran", f"{meta.get('started', '?')} to {meta.get('ended', '?')} UTC, "
                f"{meta.get('duration_s', '?')} s"],
        ["config", f"digest {cfg.get('digest', '?')}; source {src.get('kind', '?')} "
                   f"{src.get('uri', '')} {src.get('size', '')} at {src.get('rate_hz', '?')} "
                   f"pairs/s; pools {pools or 'none'}"],
        ["rig", f"{rig.get('describe', 'unknown')} from {rig.get('origin', '?')}"
         if rig else "unknown"],
        ["versions", vers]])


def _table(head: list[str], rows: list[list[Any]]) -> str:
    e = html.escape
    if not rows:
        return "<p>none</p>"
    return ("<table><tr>" + "".join(f"<th>{e(h)}</th>" for h in head) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{e(str(c))}</td>" for c in r) + "</tr>"
                      for r in rows) + "</table>")


def _energy(energy: dict[str, Any] | None) -> list[str]:
    """The power model's estimate (ledger.json's `energy`) and the motion gate's active vs
    idle time."""
    if not energy:
        return ["<p>no energy estimate (no ledger.json)</p>"]
    rows = [["board model", energy["board"]], ["watts", energy["watts"]],
            ["Wh per day", energy["wh_per_day"]], ["CPU cores busy", energy["busy_cores"]]]
    if "days_on_battery" in energy:
        rows.append(["days on the battery", energy["days_on_battery"]])
    if "active_s" in energy:
        total = energy["active_s"] + energy["idle_s"]
        share = f" ({100 * energy['active_s'] / total:.0f} %)" if total else ""
        rows += [["motion gate active (s)", f"{energy['active_s']}{share}"],
                 ["motion gate idle (s)", energy["idle_s"]]]
    per_hour = energy.get("cpu_s_per_hour", {})
    return [_table(["", "estimate"], rows),
            _table(["role", "CPU s per hour"], [[r, v] for r, v in sorted(per_hour.items())])]


def _pool_states(pools: dict[str, dict[str, Any]]) -> str:
    """Where each pool's pairs went: a column for every ledger state (the list in
    wire.pool_counters, `gated` and the drops included) that some pool holds pairs in,
    `processed` and `lost` always; a state no pool reached is left out."""
    shown = [(key, label) for key, label in LEDGER_STATES
             if key in ("processed", "lost") or any(_count(p.get(key)) for p in pools.values())]
    return _table(["pool", *(label for _key, label in shown)],
                  [[name, *(_count(p.get(key)) for key, _label in shown)]
                   for name, p in sorted(pools.items())])


def _count(value: Any) -> int:
    return value if isinstance(value, int) else 0


def render_html(s: RunSummary) -> str:
    """The page: one HTML string with its styles and SVG charts inline."""
    e = html.escape
    classes = sorted({c for per in s.per_class_hour.values() for c in per})
    per_hour = [[hour, *(per.get(c, 0) for c in classes), sum(per.values())]
                for hour, per in sorted(s.per_class_hour.items())]
    capture = [[k, s.ledger[k]] for k in ("produced", "reached_broker", "dropped_at_capture",
                                          "failed_at_capture") if k in s.ledger]
    vo = (f"{s.vo_ok} of {s.vo_total} pairs ok ({100 * s.vo_ok / s.vo_total:.0f} %)"
          if s.vo_total else "no VO results")
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        f"<title>trapflow run {e(s.run)}</title>",
        "<style>body{font-family:sans-serif;margin:2em;max-width:60em}"
        "table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;"
        "padding:2px 8px;text-align:right}th{background:#eee}</style></head><body>",
        f"<h1>trapflow run {e(s.run)}</h1>",
        f"<p>Results from {e(s.first or '-')} to {e(s.last or '-')} UTC: {s.lines} lines.</p>",
        "<h2>Run</h2>", _run_table(s.meta),
        "<h2>Detections per class per hour</h2>",
        _table(["hour (UTC)", *classes, "all"], per_hour),
        "<h2>Visits and MaxN per label per hour</h2>",
        "<p>From counts.jsonl: a visit is a track, MaxN the most tracks of a label seen at "
        "one capture time.</p>",
        _table(["hour (UTC)", "label", "visits", "MaxN", "dwell (s)"],
               [[hour, lb, int(v[0]), int(v[1]), f"{v[2]:.1f}"]
                for hour, per in sorted(s.counts_hour.items()) for lb, v in sorted(per.items())]),
        "<h2>Length-frequency per label</h2>",
        "<p>From tracks.jsonl: each measured track's length (median of its sharpest views), "
        "its range at first sighting and its speed over the ground.</p>",
        *_lengths(s),
        "<h2>Result rates per pool</h2>",
        svg_lines("pairs processed per second", s.rates, f"seconds since the first result "
                  f"({RATE_BIN_S} s bins; the last divided by the time it covers)", "pairs/s"),
        "<h2>Visual odometry</h2>", f"<p>{e(vo)}.</p>",
        svg_lines("VO path from above", {"left camera": s.vo_path} if s.vo_path else {},
                  "x (m)", "z (m)", equal=True),
        "<h2>Drops and losses</h2>", _table(["capture", "pairs"], capture),
        _pool_states(s.ledger.get("pools", {}))
        if s.ledger else "<p>no ledger.json (the run did not end cleanly)</p>",
        "<h2>Energy</h2>", *_energy(s.ledger.get("energy")),
        "<h2>Restarts</h2>", _table(["time", "node", "restart"], [list(r) for r in s.restarts]),
        "<h2>Events</h2>",
        _table(["event", "pairs", "first seq", "last seq", "results"],
               [[ev["name"], ev.get("pairs", ""), ev.get("first_seq", ""),
                 ev.get("last_seq", ""), ev.get("results", "")] for ev in s.events]),
        "</body></html>",
    ]
    return "\n".join(parts) + "\n"


def write_report(run_dir: Path, out: Path | None = None, events_folder: str = "events",
                 counts_file: str = "counts.jsonl", tracks_file: str = "tracks.jsonl") -> Path:
    """Summarize run_dir and write the page (default RUN_DIR/report.html); returns its path."""
    page = render_html(summarize(run_dir, events_folder, counts_file, tracks_file))
    target = out or run_dir / "report.html"
    try:
        target.write_text(page, encoding="utf-8")
    except OSError as exc:
        raise ReportError(f"report: cannot write {target}: {exc.strerror}; pass -o with a "
                          "writable path") from None
    return target
