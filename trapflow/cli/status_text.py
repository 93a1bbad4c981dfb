"""`trapflow status` for people: nodes, pool counters, supervision and the run's totals,
rendered with the run ledger's own model (trapflow.supervisor.ledger), as the status line
and ledger.json are."""

from __future__ import annotations

import json
import time
from typing import Any

from trapflow.supervisor import ledger as run_ledger
from trapflow.supervisor.report import energy_text
from trapflow.wire.pool_counters import POOL_COUNTERS

# The pool table's columns and their units: counts are pairs since the run started (over
# broker restarts), workers are processes, rate is results per second lately.
POOL_UNITS = {c.name: c.unit for c in POOL_COUNTERS if c.column}
# Give-ups and retries `trapflow status` lists (the newest); the JSON has them all.
TIMELINE_SHOWN = 5


def _clock(t_s: float, fmt: str) -> str:
    return time.strftime(fmt, time.gmtime(t_s))


def counts_text(counts: dict[str, Any]) -> list[str]:
    """The status reply's `counts` (the latest closed interval of counts.jsonl): per label
    its visits, MaxN and dwell, or why there is nothing to show yet."""
    latest, every = counts.get("latest"), counts["interval_s"]
    if latest is None:
        return [f"counts: no interval closed yet (one every {every:g} s, counts.jsonl)"]
    span = (f"{_clock(latest['start_s'], '%Y-%m-%d %H:%M:%S')}-"
            f"{_clock(latest['end_s'], '%H:%M:%S')} UTC")
    lines = [f"counts {span}, {latest['pairs']} pairs seen by the detector"]
    if not latest["labels"]:
        return [lines[0] + ": no animal tracked"]
    lines.append(f"{'label':<16}{'visits':>9}{'MaxN':>9}{'dwell':>9}")
    lines.append(f"{'':<16}{'(tracks)':>9}{'(tracks)':>9}{'(s)':>9}")
    for lab in latest["labels"]:
        lines.append(f"{lab['label']:<16}{lab['visits']:>9}{lab['max_n']:>9}"
                     f"{lab['dwell_s']:>9.1f}")
    return lines


def image_text(image: dict[str, Any]) -> str:
    """The image-health watch's line: its state, and its ratios to the baseline."""
    head = f"image health: {image['state']}"
    if image["state"] == "learning":
        return f"{head} (the baseline, {image['samples']} samples so far)"
    return (f"{head}; sharpness {image['sharpness']:.2f}, contrast {image['contrast']:.2f}, "
            f"brightness {image['brightness']:.2f} of the baseline; {image['samples']} "
            f"samples, {image['changes']} changes")


def supervision_text(sup: dict[str, Any]) -> list[str]:
    """The supervision part of the status reply: give-ups, the ladder, pools' runtime
    changes and the latest timeline entries."""
    lines: list[str] = []
    lines.append(f"supervision: {sup['gave_up']} give-ups, {sup['retries']} retries, "
                 f"{sup['capped']} capped restarts of essential nodes, "
                 f"{sup.get('control', 0)} runtime changes")
    lad = sup.get("ladder")
    if lad:
        how = "forced" if lad["forced"] else "auto"
        lines.append(f"ladder: level {lad['level']} ({lad['index']} of "
                     f"{len(lad['levels']) - 1}, {how}), {lad['changes']} changes; "
                     f"{lad['reason']}")
    for name, by in sup.get("recycled", {}).items():
        why = ", ".join(f"{k} {n}" for k, n in sorted(by.items()))
        lines.append(f"  pool {name:<10} workers recycled: {why}")
    for name, p in sup.get("pools", {}).items():
        params = ", ".join(f"{k}={v!r}" for k, v in p["params"].items()) or "defaults"
        off = f" (by the {p['off_by']})" if p.get("off_by") else ""
        every = f", at most 1 pair / {p['min_interval_s']:g} s" \
            if p.get("min_interval_s") else ""
        lines.append(f"  pool {name:<10} {p['state']:<9}{off} {p['count']} workers, policy "
                     f"{p['policy']}{every}, params {params}, {p['changes']} changes")
    for e in sup["timeline"][-TIMELINE_SHOWN:]:
        lines.append(f"  {e['t_s']:>8} s  {e['node']:<20} {e['kind']:<8} {e['reason']}")
    return lines


def format_status(reply: dict[str, Any], as_json: bool = False) -> str:
    """A human table of nodes and pool counters, or the JSON itself."""
    if as_json or "nodes" not in reply:
        return json.dumps(reply, indent=2)
    lines = [f"run {reply['run_dir']}  up {reply['uptime_s']} s"]
    r = reply.get("rig")
    if r:
        lines.append(f"rig calib {r['calib']}: {r['width']}x{r['height']}, fx {r['fx']:.1f} "
                     f"fy {r['fy']:.1f} cx {r['cx']:.1f} cy {r['cy']:.1f}, baseline "
                     f"{r['baseline_m']:.3f} m, from {r['origin']}")
    lines.append(f"{'node':<22} {'pid':>7} {'state':<12} {'restarts':>8}  reason")
    lines.append(f"{'':<22} {'':>7} {'(lifecycle)':<12} {'(count)':>8}")
    for n in reply["nodes"]:
        lines.append(f"{n['name']:<22} {n['pid'] or '-':>7} {n['state']:<12} "
                     f"{n['restarts']:>8}  {n['reason']}")
    stats = reply.get("stats")
    if stats:
        lines.append(f"pairs in {stats['pairs_in']} ({stats['rate_in']} pairs/s), "
                     f"malformed {stats['malformed']} messages")
        lines.append(f"{'pool':<10}" + "".join(f"{k:>11}" for k in POOL_UNITS))
        lines.append(f"{'':<10}" + "".join(f"{'(' + u + ')':>11}" for u in POOL_UNITS.values()))
        for name, p in stats["pools"].items():
            lines.append(f"{name:<10}" + "".join(f"{p.get(k, 0):>11}" for k in POOL_UNITS))
        remote = stats.get("remote") or []
        if remote:
            lines.append(f"{'remote worker':<34} {'host':<16} {'pool':<10} {'state':<8} "
                         f"{'processed':>9} {'rate':>7}  reason")
        for r in remote:
            lines.append(f"{r['worker']:<34} {r['host']:<16} {r['pool']:<10} {r['state']:<8} "
                         f"{r.get('processed', 0):>9} {r.get('rate', 0.0):>7}  "
                         f"{r.get('reason', '')}")
        if stats.get("image"):
            lines.append(image_text(stats["image"]))
    if reply.get("counts"):
        lines += counts_text(reply["counts"])
    if reply.get("supervision"):
        lines += supervision_text(reply["supervision"])
    if reply.get("ledger"):
        lines.append(run_ledger.totals_text(reply["ledger"]).rstrip("\n"))
        if reply["ledger"].get("energy"):
            lines.append(energy_text(reply["ledger"]["energy"]).rstrip("\n"))
    return "\n".join(lines)
