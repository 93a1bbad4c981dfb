"""Benchmark of the motion gate: CPU per pair of each background method at 1280x720, and on
synthetic sequences with truth (static rig) what the gate would withhold; then whole
pipelines (benchmarks/gate_pipeline.py): sequences rendered first with `trapflow dataset
synth` and replayed as an image folder, gated default against `gate: always`, in one run.
Writes gate.json and gate.md into --out and prints the tables.

Usage: python -m benchmarks.gate [--quick] [--pairs 1800 --seeds 11,12,13 --out bench-results
                                  --pipeline-pairs 900 --size 1280x720]
(--quick: 300 pairs a sequence, one seed, 2 rounds, no pipeline part)

Miss rate: pairs with an animal in view that the gated pool would not get (after pre-roll,
hold and keep-alive). Two recognisers are simulated: `gate` alone (no tracks), and `tracks`
(an ideal recogniser: an animal in a fed pair starts a track that stays alive while the
animal is in view), what the observations' tracks give the gate.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks import gate_pipeline  # noqa: E402
from benchmarks import harness as h  # noqa: E402
from trapflow.calibration.camera import StereoRig  # noqa: E402
from trapflow.gate.motion import METHODS, MotionConfig, MotionDetector  # noqa: E402
from trapflow.gate.policy import Feed, GateConfig, GateState  # noqa: E402
from trapflow.synth.options import SynthOptions  # noqa: E402
from trapflow.synth.render import World  # noqa: E402
from trapflow.wire.messages import Truth  # noqa: E402

ANIMALS = ("crab", "scallop")
RATE_HZ = 10.0
POOL = "mono"


def animals(truth: Truth) -> set[int]:
    """Animal ids in view (at least a fifth visible)."""
    return {o.id for o in truth.objects if o.label in ANIMALS and o.occluded < 0.8}


def cost(frames: list[np.ndarray], method: str, rounds: int) -> dict[str, float]:
    """CPU microseconds per pair (process time, resize included), median and 90th pct."""
    det = MotionDetector(MotionConfig(method=method))
    for f in frames:  # warm up: background built, caches hot
        det.update(f)
    ts = []
    for _ in range(rounds):
        for f in frames:
            t0 = time.process_time_ns()
            det.update(f)
            ts.append(time.process_time_ns() - t0)
    return {"median_us": round(float(np.median(ts)) / 1e3, 1),
            "p90_us": round(float(np.percentile(ts, 90)) / 1e3, 1), "pairs": len(ts)}


@dataclass
class Tally:
    """What one method's gate did on one sequence."""

    pairs: int = 0
    animal_pairs: int = 0
    animal_withheld: int = 0
    empty_pairs: int = 0
    empty_withheld: int = 0
    empty_motion: int = 0  # empty pairs the detector said moved
    fed: int = 0
    seen: set[int] = field(default_factory=set)  # animal ids in view at least once
    fed_ids: set[int] = field(default_factory=set)  # animal ids in at least one fed pair

    def add(self, other: Tally) -> None:
        for k in ("pairs", "animal_pairs", "animal_withheld", "empty_pairs", "empty_withheld",
                  "empty_motion", "fed"):
            setattr(self, k, getattr(self, k) + getattr(other, k))

    def summary(self, ids_seen: int, ids_fed: int) -> dict[str, float | int]:
        return {
            "pairs": self.pairs,
            "fed_fraction": round(self.fed / max(self.pairs, 1), 4),
            "miss_rate": round(self.animal_withheld / max(self.animal_pairs, 1), 4),
            "animal_pairs": self.animal_pairs,
            "animals": ids_seen,
            "animals_fed": ids_fed,
            "empty_withheld": round(self.empty_withheld / max(self.empty_pairs, 1), 4),
            "empty_motion": round(self.empty_motion / max(self.empty_pairs, 1), 4),
            "empty_pairs": self.empty_pairs,
        }


class Run:
    """One method's detector and gate over one sequence, with the simulated tracker."""

    def __init__(self, method: str, tracks: bool, gate: GateConfig) -> None:
        self.det = MotionDetector(MotionConfig(method=method))
        self.gate = GateState({POOL: gate})
        self.tracks = tracks
        self.tally = Tally()
        self.in_view: dict[int, set[int]] = {}  # seq -> animal ids (pre-roll pairs come back)
        self.alive: set[int] = set()

    def step(self, seq: int, left: np.ndarray, ids: set[int], now: float) -> None:
        res = self.det.update(left)
        t = self.tally
        self.in_view[seq] = ids
        self.in_view.pop(seq - 200, None)
        t.pairs += 1
        t.seen |= ids
        if self.tracks:
            for tid in self.alive - ids:
                self.gate.track_ended(tid, now)
            self.alive &= ids
            for tid in self.alive:
                self.gate.track_alive(tid, now)
        fed_now = False
        for a in self.gate.pair(seq, res.motion, res.score, now):
            if isinstance(a, Feed):
                t.fed += 1
                fed_ids = self.in_view.get(a.seq, set())
                t.fed_ids |= fed_ids
                if a.seq == seq:
                    fed_now = True
                else:  # a pre-roll pair: it was counted withheld when it came
                    prev = self.in_view.get(a.seq, set())
                    if prev:
                        t.animal_withheld -= 1
                    else:
                        t.empty_withheld -= 1
                if self.tracks:
                    self.alive |= fed_ids & ids  # a track starts if the animal is still here
        if ids:
            t.animal_pairs += 1
            t.animal_withheld += not fed_now
        else:
            t.empty_pairs += 1
            t.empty_withheld += not fed_now
            t.empty_motion += res.motion


def frames(options: SynthOptions, seed: int, pairs: int, flicker: bool
           ) -> Iterator[tuple[int, np.ndarray, set[int]]]:
    rig = StereoRig.from_fov(1280, 720, 70.0, 0.12)
    world = World(rig, seed=seed, moving=False, rate_hz=RATE_HZ, options=options)
    rng = np.random.default_rng(seed)
    lamp = 1.0
    for i in range(pairs):
        left, _right, truth = world.render(i)
        if flicker:  # 5 % flicker every pair, and a lamp step of -30 %/+40 % every 20 s
            if i and i % 200 == 0:
                lamp = 0.7 if lamp == 1.0 else 1.0
            left = cv2.convertScaleAbs(left, alpha=lamp * float(rng.uniform(0.95, 1.05)))
        yield i, left, animals(truth)


SCENARIOS: dict[str, tuple[SynthOptions, bool]] = {
    "default": (SynthOptions(), False),  # the world's default empty fraction and snow
    "empty": (SynthOptions(density=0.0), False),
    "empty_max_snow": (SynthOptions(density=0.0, snow=5.0), False),
    "empty_flicker": (SynthOptions(density=0.0), True),
}


def quality(seeds: list[int], pairs: int, gate: GateConfig) -> dict[str, object]:
    out: dict[str, object] = {}
    for name, (opts, flicker) in SCENARIOS.items():
        runs = {(m, tr): Tally() for m in METHODS for tr in (False, True)}
        ids: dict[tuple[str, bool], tuple[int, int]] = {k: (0, 0) for k in runs}
        use = seeds if name == "default" else seeds[:1]
        n = pairs if name == "default" else min(pairs, 600)
        for seed in use:
            live = {k: Run(k[0], k[1], gate) for k in runs}
            for seq, left, in_view in frames(opts, seed, n, flicker):
                for r in live.values():
                    r.step(seq, left, in_view, seq / RATE_HZ)
            for k, r in live.items():
                runs[k].add(r.tally)
                s, f = ids[k]
                ids[k] = (s + len(r.tally.seen), f + len(r.tally.fed_ids & r.tally.seen))
        out[name] = {f"{m}{'+tracks' if tr else ''}": runs[(m, tr)].summary(*ids[(m, tr)])
                     for m, tr in runs}
        h.log("gate", f"quality: {name}")
    return out


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="300 pairs, one seed, no pipeline part")
    ap.add_argument("--pairs", type=int, default=1800, help="pairs per default sequence")
    ap.add_argument("--seeds", default="11,12,13", help="held-out world seeds")
    ap.add_argument("--rounds", type=int, default=10, help="cost: passes over 100 pairs")
    ap.add_argument("--pipeline-pairs", type=int, default=900,
                    help="pairs per replayed sequence of the pipeline part (0: skip it)")
    ap.add_argument("--size", default="1280x720", help="pipeline part: rendered pair size")
    ap.add_argument("--battery-wh", type=float, default=1000.0,
                    help="pipeline part: battery capacity for days on a Pi 5")
    ap.add_argument("--busy-rates", default="",
                    help="pipeline part: also gate the default world at these "
                         "gate.busy_rate_hz, comma-separated (how the default was chosen)")
    args = ap.parse_args()
    if args.quick:
        args.pairs, args.seeds, args.rounds, args.pipeline_pairs = 300, "11", 2, 0
    cv2.setNumThreads(1)
    rig = StereoRig.from_fov(1280, 720, 70.0, 0.12)
    world = World(rig, seed=5, moving=False, rate_hz=RATE_HZ, options=SynthOptions())
    sample = [world.render(i)[0] for i in range(100)]
    costs = {m: cost(sample, m, args.rounds) for m in METHODS}
    h.log("gate", "cost per pair measured")
    gate = GateConfig()
    result = {
        "bench": "gate",
        "size": "1280x720",
        "threads": cv2.getNumThreads(),
        "rate_hz": RATE_HZ,
        # The simulation measures the detector: no busy rate (GateConfig's 0).
        "gate": {"pre_roll": gate.pre_roll, "keepalive_s": gate.keepalive_s,
                 "hold_s": gate.hold_s, "busy_rate_hz": gate.busy_rate_hz},
        "motion": {k: v for k, v in vars(MotionConfig()).items() if k != "method"},
        "cost_per_pair": costs,
        "quality": quality([int(s) for s in args.seeds.split(",")], args.pairs, gate),
    }
    if args.pipeline_pairs:
        w, ht = (int(v) for v in args.size.split("x"))
        result["pipeline"] = gate_pipeline.run_all(
            args.out / "gate-pipeline", args.pipeline_pairs, (w, ht), RATE_HZ, args.battery_wh,
            tuple(float(r) for r in args.busy_rates.split(",") if r))
    tables = results(result)
    h.write(args.out, "gate", tables)
    print(h.markdown(tables))


def results(r: dict[str, Any]) -> list[h.Result]:
    """Cost per method; per scenario what each method's gate fed and withheld; the
    pipelines' CPU, energy and recall when they ran."""
    cost_t = h.Result("gate", f"Motion gate: cost per pair ({r['size']}, one thread)",
                      key="method", data=r)
    for m, c in r["cost_per_pair"].items():
        cost_t.add(m, median=h.Figure(c["median_us"], "us", digits=1),
                   p90=h.Figure(c["p90_us"], "us", digits=1), pairs=h.Figure(c["pairs"]))
    out = [cost_t]
    for name, by in r["quality"].items():
        q = h.Result("gate", f"Gate on sequence '{name}'", key="method", notes=[
            "fed: share of pairs the gated pool got; missed: animal pairs withheld; "
            "animals fed: animals in view in at least one fed pair, of those seen."])
        for m, s in by.items():
            q.add(m, fed=h.Figure(round(100 * s["fed_fraction"], 2), "%"),
                  missed=h.Figure(round(100 * s["miss_rate"], 2), "%"),
                  **{"animals fed": h.Figure(f"{s['animals_fed']} / {s['animals']}"),
                     "empty withheld": h.Figure(round(100 * s["empty_withheld"], 2), "%"),
                     "empty with motion": h.Figure(round(100 * s["empty_motion"], 2), "%")})
        out.append(q)
    if "pipeline" in r:
        out.append(gate_pipeline.result(r["pipeline"]))
    return out


if __name__ == "__main__":
    main()
