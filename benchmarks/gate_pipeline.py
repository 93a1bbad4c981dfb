"""The gate benchmark's pipeline part: sequences rendered first with `trapflow dataset synth`
(static rig), then replayed as an image folder at the capture rate through whole pipelines,
the gated default against the same with `gate: always` on mono and stereo, one after the
other in one run. From each run's ledger.json: CPU seconds per role (the supervisor's meter),
the gate's active and idle time; from results.jsonl and the sequence's truth.jsonl: which
animals (truth ids) mono detected at least once. `busy_rates` adds gated runs of the default
sequence at each gate.busy_rate_hz (what the default was chosen by).

Run by benchmarks/gate.py (`scripts/bench.sh` part `gate`), which writes its table; writes
no file of its own beyond the rendered sequences and the run directories under its folder.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks import harness as h
from trapflow.power.energy import BOARDS, cpu_from_rates, days_on_battery, estimate

RECOGNISERS = ("mono", "stereo")
ANIMALS = ("crab", "scallop")
IOU_HIT = 0.3  # a detection box overlapping a truth box this much found that animal
# The original ROS 2 trap's per-frame costs on a Pi 5 (issue 25): the second scenario.
ROS2_COST_S = {"mono": 0.060, "stereo": 10.7}
# Sequences: name -> world options (static rig).
SEQUENCES = {"default": [], "empty": ["density=0"], "snow_max": ["density=0", "snow=5"]}


def _iou(a: list[float], b: list[float]) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def render(folder: Path, options: list[str], pairs: int, size: tuple[int, int], rate: float,
           seed: int) -> None:
    """A sequence with truth, rendered before any pipeline runs (rendering is not measured)."""
    opts = [a for o in options for a in ("-o", o)]
    subprocess.run([sys.executable, "-m", "trapflow", "dataset", "synth", str(folder),
                    "--frames", str(pairs), "--seed", str(seed), "--rate", str(rate),
                    "--width", str(size[0]), "--height", str(size[1]), "--overwrite", *opts],
                   check=True, capture_output=True, text=True)


def replay(folder: Path, run_dir: Path, gated: bool, rate: float, pairs: int,
           busy_rate: float | None = None) -> dict[str, Any]:
    """One pipeline over the folder at `rate` (gate.busy_rate_hz: `busy_rate`, None: the
    default); returns its ledger.json."""
    cfg = run_dir.parent / f"{run_dir.name}.yaml"
    pools = {} if gated else {p: {"gate": "always"} for p in RECOGNISERS}
    gate = {} if busy_rate is None else {"gate": {"busy_rate_hz": busy_rate}}
    cfg.write_text(json.dumps({"pools": pools, "log_level": "WARNING", **gate}))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run([sys.executable, "-m", "trapflow", "start", "--run-dir", str(run_dir),
                    "--config", str(cfg), "--source", f"images:{folder}", "--rate", str(rate)],
                   check=True, capture_output=True, text=True, env=env,
                   timeout=pairs / rate * 6 + 120)
    ledger: dict[str, Any] = json.loads((run_dir / "ledger.json").read_text())
    return ledger


def detected_ids(folder: Path, run_dir: Path) -> tuple[set[int], set[int]]:
    """(animal ids in view at least once, those a mono box found at least once)."""
    truth: dict[int, list[dict[str, Any]]] = {}
    for line in (folder / "truth.jsonl").read_text().splitlines():
        t = json.loads(line)
        truth[t["seq"]] = [o for o in t.get("objects", [])
                           if o["label"] in ANIMALS and o["occluded"] < 0.8]
    found: set[int] = set()
    for line in (run_dir / "results.jsonl").read_text().splitlines():
        body = json.loads(line).get("mono_ir")
        if not body or len(body.get("box", [])) != 4:
            continue
        for obj in truth.get(body["seq"], []):
            if _iou(body["box"], obj["box"]) >= IOU_HIT:
                found.add(obj["id"])
    return {o["id"] for objs in truth.values() for o in objs}, found


def summary(ledger: dict[str, Any], battery_wh: float) -> dict[str, Any]:
    """CPU of the recognisers and of everything, per hour; watts and days on a Pi 5 battery,
    measured and with the original trap's per-frame costs at the pairs each pool got."""
    e = ledger["energy"]
    wall = e["wall_s"]
    cpu = e["cpu_s"]
    rec = sum(cpu.get(p, 0.0) for p in RECOGNISERS)
    pi5 = estimate(BOARDS["pi5"], cpu, wall)
    fed = {p: (ledger["pools"][p]["processed"] + ledger["pools"][p]["dropped_by_policy"]) / wall
           for p in RECOGNISERS}  # pairs the gate let through (a latest pool drops some)
    # One worker per pool takes at most one pair per its cost: a `latest` pool drops the rest.
    ros2_cpu = cpu_from_rates(ROS2_COST_S, {p: min(r, 1.0 / ROS2_COST_S[p])
                                            for p, r in fed.items()}, wall)
    ros2 = estimate(BOARDS["pi5"], {**{k: v for k, v in cpu.items()
                                        if k not in RECOGNISERS}, **ros2_cpu}, wall)
    out = {"wall_s": wall, "produced": ledger["produced"],
           "recognisers_cpu_s": round(rec, 2), "cpu_s": cpu,
           "pipeline_cpu_s_per_hour": round(sum(cpu.values()) * 3600 / wall, 1),
           "recognisers_fed_per_s": {p: round(v, 3) for p, v in fed.items()},
           "pi5_watts": round(pi5.watts, 2),
           "pi5_days": round(days_on_battery(pi5.wh_per_day, battery_wh, 0.8), 1),
           "ros2_costs_pi5_watts": round(ros2.watts, 2),
           "ros2_costs_pi5_days": round(days_on_battery(ros2.wh_per_day, battery_wh, 0.8), 1)}
    if "active_s" in e:
        total = e["active_s"] + e["idle_s"]
        out["gate_active_share"] = round(e["active_s"] / total, 4) if total else 0.0
    return out


def run_all(folder: Path, pairs: int, size: tuple[int, int], rate: float,
            battery_wh: float, busy_rates: tuple[float, ...] = ()) -> dict[str, Any]:
    """Render every sequence, then replay each gated and ungated (the default sequence
    also gated at each of `busy_rates`); ratios in one run."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, (name, options) in enumerate(SEQUENCES.items()):
        render(folder / name, options, pairs, size, rate, seed=11 + i)
    out: dict[str, Any] = {"pairs": pairs, "size": f"{size[0]}x{size[1]}", "rate_hz": rate,
                           "battery_wh": battery_wh, "usable": 0.8,
                           "load_before": os.getloadavg()}
    for name in SEQUENCES:
        runs: dict[str, Any] = {}
        kinds: list[tuple[str, bool, float | None]] = [("gated", True, None)]
        if name != "snow_max":
            kinds.append(("ungated", False, None))
        if name == "default":
            kinds += [(f"gated_busy_{r:g}", True, r) for r in busy_rates]
        for kind, gated, busy in kinds:
            run_dir = folder / f"run-{name}-{kind}"
            t0 = time.monotonic()
            ledger = replay(folder / name, run_dir, gated, rate, pairs, busy)
            runs[kind] = summary(ledger, battery_wh)
            seen, found = detected_ids(folder / name, run_dir)
            runs[kind]["animals"], runs[kind]["animals_detected"] = len(seen), sorted(found)
            runs[kind]["took_s"] = round(time.monotonic() - t0, 1)
            runs[kind]["load"] = os.getloadavg()
        if "ungated" in runs:
            u = runs["ungated"]
            base = set(u["animals_detected"])
            for kind, gated, _busy in kinds:
                if not gated:
                    continue
                g = runs[kind]
                g["recognisers_cpu_ratio"] = round(
                    g["recognisers_cpu_s"] / max(u["recognisers_cpu_s"], 1e-9), 3)
                g["animal_recall_vs_ungated"] = (
                    round(len(base & set(g["animals_detected"])) / len(base), 4)
                    if base else None)
        out[name] = runs
        h.log("gate", f"pipeline: {name}")
    out["load_after"] = os.getloadavg()
    return out


def result(p: dict[str, Any]) -> h.Result:
    """Per sequence and run: the recognisers' CPU, the pipeline's per hour, a Pi 5's watts
    and days on the battery (measured, and with the original trap's costs), recall."""
    r = h.Result("gate", f"Motion gate, whole pipelines ({p['pairs']} pairs {p['size']} at "
                 f"{p['rate_hz']:g} pairs/s, battery {p['battery_wh']:g} Wh, "
                 f"{100 * p['usable']:.0f} % usable)", key="sequence, run", notes=[
        "recognisers x: their CPU against the ungated run of the same sequence; recall: "
        "animals mono detected, against the ungated run; ROS 2 days: the original trap's "
        "per-frame costs at the pairs each pool got."])
    for name, runs in p.items():
        if not isinstance(runs, dict) or name == "load_before":
            continue
        for kind, x in runs.items():
            recall = x.get("animal_recall_vs_ungated")
            r.add(f"{name}, {kind}", **{
                "recognisers CPU": h.Figure(x["recognisers_cpu_s"], "s"),
                "recognisers x": h.Figure(x.get("recognisers_cpu_ratio"), digits=3),
                "pipeline CPU": h.Figure(x["pipeline_cpu_s_per_hour"], "s/h", digits=1),
                "Pi 5": h.Figure(x["pi5_watts"], "W"),
                "Pi 5 days": h.Figure(x["pi5_days"], digits=1),
                "ROS 2 days": h.Figure(x["ros2_costs_pi5_days"], digits=1),
                "recall": h.Figure(None if recall is None else round(100 * recall, 2), "%"),
                "gate active": h.Figure(None if "gate_active_share" not in x else
                                        round(100 * x["gate_active_share"], 2), "%")})
    return r
