"""Tunes trapflow's tracker on the tracking bench's development seeds only (never the
held-out ones): coordinate descent over the thresholds, the gaps and the motion model's
noise, scored by the mean of HOTA and IDF1 at both detector rates, pooled over sequences.

    python -m benchmarks.tune_tracking [--seeds N] [--frames N] [--jobs N] [--rounds N]
                                       [--set KEY=VALUE ...] [--keys KEY,KEY...]

--set starts from other values than TrackerConfig's defaults; --keys searches only those.

Prints every configuration tried with its score and the best one; writes
bench-results/tracking-tune.json. Sequences are cached in bench-results/tracking-cache/
(rendering the synthetic world is most of a first run). Needs the same extras as
benchmarks/tracking.py. A tuner, not a benchmark: it keeps its own options.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from benchmarks.tracking import (
    DEV_SEEDS,
    HELD_OUT_SEEDS,
    SynthSequence,
    evaluate,
    make_sequence,
    run_trapflow,
)
from trapflow.tracking.tracker import TrackerConfig

# The values tried per parameter; noise.* are the Kalman filter's Noise fields.
GRID: dict[str, Sequence[float]] = {
    "max_gap_s": (0.75, 1.0, 1.5, 2.0, 3.0, 4.0),
    "iou_gate": (0.05, 0.1, 0.15, 0.2, 0.3),
    "dist_gate": (0.0, 9.5, 13.0, 20.0),
    "dup_iou": (0.5, 0.6, 0.7, 1.0),
    "min_hits": (1, 2, 3),
    "tentative_gap_s": (0.0, 0.1, 0.25, 0.5, 1.0),
    "high": (0.4, 0.5, 0.6),
    "low": (0.1, 0.2, 0.3),
    "noise.measure": (0.02, 0.03, 0.05, 0.08, 0.1, 0.12, 0.16),
    "noise.accel": (0.25, 0.5, 1.0, 2.0, 4.0),
    "noise.speed0": (0.25, 0.5, 1.0, 2.0),
    "noise.turn": (0.0, 0.25, 0.5, 1.0, 2.0),
}


def with_value(cfg: TrackerConfig, key: str, value: float) -> TrackerConfig:
    if key.startswith("noise."):
        noise = dataclasses.replace(cfg.noise, **{key[6:]: value})  # floats all
        return dataclasses.replace(cfg, noise=noise)
    change: dict[str, Any] = {key: int(value) if key == "min_hits" else value}
    return dataclasses.replace(cfg, **change)


def value_of(cfg: TrackerConfig, key: str) -> float:
    return float(getattr(cfg.noise, key[6:]) if key.startswith("noise.") else getattr(cfg, key))


def load(seed: int, frames: int, cache: Path) -> SynthSequence:
    path = cache / f"{seed}-{frames}.pickle"
    if path.is_file():
        seq: SynthSequence = pickle.loads(path.read_bytes())
        return seq
    seq = make_sequence(seed, frames)
    cache.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(seq))
    return seq


_SEQS: list[SynthSequence] = []


def _init(seeds: list[int], frames: int, cache: str) -> None:
    _SEQS[:] = [load(s, frames, Path(cache)) for s in seeds]


def _score(cfg: TrackerConfig) -> dict[str, Any]:
    res = evaluate(_SEQS, {"trapflow": run_trapflow(cfg)})
    per = {rate: {k: res[rate]["trapflow"][k] for k in ("HOTA", "IDF1")} for rate in res}
    objective = sum((m["HOTA"] + m["IDF1"]) / 2 for m in per.values()) / len(per)
    return {"objective": objective, "rates": per}


def describe(cfg: TrackerConfig) -> dict[str, float]:
    return {k: value_of(cfg, k) for k in GRID}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=len(DEV_SEEDS),
                    help="development seeds used, from the first")
    ap.add_argument("--frames", type=int, default=900)
    ap.add_argument("--jobs", type=int, default=1, help="processes scoring in parallel")
    ap.add_argument("--rounds", type=int, default=2, help="passes over the parameters")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="start value of a parameter (a GRID key)")
    ap.add_argument("--keys", default=",".join(GRID), help="parameters searched, comma-separated")
    ap.add_argument("--out", type=Path, default=Path("bench-results/tracking-tune.json"))
    args = ap.parse_args()
    keys = [k for k in args.keys.split(",") if k]
    unknown = [k for k in keys + [kv.partition("=")[0] for kv in args.set] if k not in GRID]
    if unknown:
        ap.error(f"unknown parameters {unknown}: expected some of {list(GRID)}")
    seeds = list(DEV_SEEDS[: args.seeds])
    assert not set(seeds) & set(HELD_OUT_SEEDS), "tuning must never see a held-out seed"
    cache = args.out.parent / "tracking-cache"
    for s in seeds:  # render once, before the workers start
        load(s, args.frames, cache)
    tried: dict[str, dict[str, Any]] = {}
    best = TrackerConfig()
    for kv in args.set:
        key, _, value = kv.partition("=")
        best = with_value(best, key, float(value))
    with ProcessPoolExecutor(args.jobs, initializer=_init,
                             initargs=(seeds, args.frames, str(cache))) as pool:
        def run(cfgs: list[TrackerConfig]) -> None:
            todo = [c for c in cfgs if repr(c) not in tried]
            for c, got in zip(todo, pool.map(_score, todo), strict=True):
                tried[repr(c)] = {"config": describe(c), **got}
                rates = " ".join(f"{r} {m['HOTA'] * 100:.1f}/{m['IDF1'] * 100:.1f}"
                                 for r, m in got["rates"].items())
                print(f"{got['objective'] * 100:6.2f}  {rates}  {describe(c)}", flush=True)

        run([best])
        for _ in range(args.rounds):
            changed = False
            for key in keys:
                values = GRID[key]
                cands = [with_value(best, key, v) for v in values]
                run(cands)
                top = max(cands, key=lambda c: tried[repr(c)]["objective"])
                if tried[repr(top)]["objective"] > tried[repr(best)]["objective"]:
                    best, changed = top, True
            if not changed:
                break
    print(f"best {tried[repr(best)]['objective'] * 100:.2f}: {describe(best)}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"seeds": seeds, "frames": args.frames,
                                    "best": tried[repr(best)],
                                    "tried": list(tried.values())}, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
