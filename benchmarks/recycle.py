"""Recycling bench: what a worker's per-pair health check costs (its RSS read through
psutil, /proc/self/statm), and what a recycle costs its pool in a real run: wall seconds
from a worker's goodbye to its successor being active (trapflow.log), and the capture-time
gap between the last pair a worker answered and the first its successor answered.

Writes recycle.json and recycle.md into --out and prints the table.
Usage: python -m benchmarks.recycle [--quick] [--out bench-results] [--reads 20000]
       [--duration 8]
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil
import yaml

from benchmarks import harness as h

REPO = Path(__file__).resolve().parent.parent


def rss_read_us(reads: int) -> dict[str, Any]:
    """Microseconds per memory_info() call, median and 95th percentile of 20 batches."""
    proc = psutil.Process()
    per_batch = []
    batch = max(reads // 20, 1)
    for _ in range(20):
        t0 = time.perf_counter_ns()
        for _ in range(batch):
            proc.memory_info()
        per_batch.append((time.perf_counter_ns() - t0) / batch / 1000)
    per_batch.sort()
    s = h.summarise(per_batch, "iqr")
    return {"median_us": round(s.median, 2), "iqr_us": [round(s.low, 2), round(s.high, 2)],
            "p95_us": round(per_batch[int(0.95 * (len(per_batch) - 1))], 2)}


def recycle_gaps(duration: float) -> dict[str, Any]:
    """A run whose one worker keeps 20 MiB per pair and is recycled past 160 MiB: seconds
    between its last result and its successor's first, and the ledger's counts."""
    with tempfile.TemporaryDirectory(prefix="tfb-") as tmp:
        cfg = Path(tmp) / "c.yaml"
        cfg.write_text(yaml.safe_dump({
            "source": {"width": 320, "height": 240, "rate_hz": 15.0},
            "pools": {"mono": {"count": 0}, "stereo": {"count": 0}, "vo": {"count": 0},
                      "grow": {"plugin": "tests.integration.recycle_plugins:Grow",
                               "policy": "fifo:8", "max_rss_mb": 160,
                               "params": {"mb": 20}}}}))
        run = Path(tmp) / "run"
        subprocess.run([sys.executable, "-m", "trapflow", "start", "--config", str(cfg),
                        "--run-dir", str(run), "--duration", str(duration)], cwd=REPO,
                       check=True, capture_output=True, timeout=duration + 120)
        rows = [json.loads(line)["grow"] for line in
                (run / "results.jsonl").read_text().splitlines() if line.strip()]
        ledger = json.loads((run / "ledger.json").read_text())
        down = _replacement_s((run / "trapflow.log").read_text())
    # Result timestamps are capture times; a pid change marks a successor's first answer.
    stamps = [(r["pid"], r["timestamp"]) for r in rows]
    gaps = []
    for (pid_a, t_a), (pid_b, t_b) in zip(stamps, stamps[1:], strict=False):
        if pid_a != pid_b:
            gaps.append(_seconds(t_b) - _seconds(t_a))
    pool = ledger["pools"]["grow"]
    return {"results": len(rows), "workers": len({p for p, _ in stamps}),
            "recycled": pool["recycled"], "lost": pool["lost"], "restarts": pool["restarts"],
            "dropped_by_policy": pool["dropped_by_policy"],
            "replacement_wall_s": _spread(down), "capture_gap_s": _spread(gaps)}


def _spread(values: list[float]) -> dict[str, float | None]:
    return {"median": round(statistics.median(values), 2) if values else None,
            "max": round(max(values), 2) if values else None, "n": len(values)}


def _replacement_s(log_text: str) -> list[float]:
    """Seconds from each recycled worker's last state (finalized) to its successor's
    active, from the log's own timestamps."""
    out, left = [], None
    for line in log_text.splitlines():
        if "worker:grow:0: finalized (recycled" in line:
            left = _seconds(line[:23].replace(",", "."))
        elif "worker:grow:0: active" in line and left is not None:
            out.append(_seconds(line[:23].replace(",", ".")) - left)
            left = None
    return out


def _seconds(stamp: str) -> float:
    hms = stamp.split(" ")[1]
    hours, minutes, seconds = hms.split(":")
    return int(hours) * 3600 + int(minutes) * 60 + float(seconds)


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="2000 reads, a 5 s run")
    ap.add_argument("--reads", type=int, default=20000)
    ap.add_argument("--duration", type=float, default=8.0)
    args = ap.parse_args()
    if args.quick:
        args.reads, args.duration = 2000, 5.0
    out = {"rss_read": rss_read_us(args.reads), "run": recycle_gaps(args.duration),
           "cpus": psutil.cpu_count(), "load1": round(psutil.getloadavg()[0], 2)}
    results = results_of(out)
    h.write(args.out, "recycle", results)
    print(h.markdown(results))


def results_of(out: dict[str, Any]) -> list[h.Result]:
    rss, run = out["rss_read"], out["run"]
    check = h.Result("recycle", "Worker recycling", key="health check", data=out, notes=[
        "One memory_info() call, the per-pair health check: median of 20 batches "
        "[interquartile range]."])
    low, high = rss.get("iqr_us") or (None, None)
    check.add("RSS read", median=h.Figure(rss["median_us"], "us", low, high),
              p95=h.Figure(rss["p95_us"], "us"))
    r = h.Result("recycle", key="recycle", notes=[
        "Replacement: a recycled worker's last state to its "
        "successor's active (the log's stamps); capture gap: capture time between the last "
        f"pair a worker answered and the first its successor answered. Run: {run['results']} "
        f"results from {run['workers']} workers, recycled {run['recycled']}, lost "
        f"{run['lost']}, restarts {run['restarts']}, dropped by policy "
        f"{run['dropped_by_policy']}; {out['cpus']} cores, load {out['load1']}."])
    for label, key in (("replacement", "replacement_wall_s"), ("capture gap", "capture_gap_s")):
        s = run[key]
        r.add(label, median=h.Figure(s["median"], "s"), max=h.Figure(s["max"], "s"),
              n=h.Figure(s["n"]))
    return [check, r]


if __name__ == "__main__":
    main()
