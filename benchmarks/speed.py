"""Benchmark of track speeds over the ground on the synthetic world, with the rig still and
with the rig moving, against the world's truth.

Every pair is rendered and goes through the packaged stereo VO plugin; every `--every`-th
pair's animals (truth boxes of animals at most 10 % hidden, wholly inside the image) are
measured by the stereo measurement and grouped into tracks by their true identity, so the
numbers are the measurement's and the rig-motion removal's, not the tracker's. A track's
speed is the observation stage's own (trapflow.tracking.stage.aggregate: a straight line
through its 3-D positions, in VO's world frame); the truth is the same line through the
animal's true positions in the true world frame at the same times. Only tracks whose true
speed is at least --min-speed m/s are scored (a resting scallop has no relative error).
Seeds given with --seeds; the defaults are held out (never used while developing).

Writes speed.json and speed.md into --out and prints the table.
Usage: python -m benchmarks.speed [--quick] [--seeds S,S] [--pairs 300] [--rate 10]
       [--every 2] [--min-speed 0.02] [--out bench-results]   (--quick: 100 pairs, one seed)
"""

from __future__ import annotations

import time
from typing import Any

import cv2
import numpy as np

from benchmarks import harness as h
from benchmarks.measure import usable
from trapflow.calibration.camera import StereoRig
from trapflow.measure.stereo import Measured, measure
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.tracking.rigpose import RigPoses
from trapflow.tracking.stage import MIN_SPEED_VIEWS, View, aggregate

HELD_OUT_SEEDS = (9111, 9112, 9113, 9114)


def run_sequence(seed: int, moving: bool, pairs: int, rate_hz: float,
                 every: int) -> tuple[dict[int, list[View]], dict[int, list[View]], RigPoses,
                                      RigPoses, dict[str, float]]:
    """Measured and true views per animal, VO's and the true poses, CPU ms per stage."""
    from trapflow_workers.stereo_vo import StereoOdometry

    from trapflow.testing.kit import make_context, make_pair

    rig = StereoRig.from_fov(640, 360, 70.0, 0.12)
    opts = SynthOptions(density=2.0, empty_fraction=0.0, episode_s=12.0)
    world = World(rig, seed=seed, moving=moving, rate_hz=rate_hz, options=opts)
    vo = StereoOdometry()
    vo.configure({}, make_context(rig, pool="vo"))
    measured: dict[int, list[View]] = {}
    true: dict[int, list[View]] = {}
    vo_poses, true_poses = RigPoses(), RigPoses()
    cpu = {"vo_ms": 0.0, "measure_ms": 0.0, "boxes": 0.0}
    for i in range(pairs):
        left, right, truth = world.render(i)
        t_s = i / rate_hz
        gl = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)
        gr = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)
        t0 = time.process_time()
        got = vo.process(make_pair(gl, gr, seq=i))
        cpu["vo_ms"] += (time.process_time() - t0) * 1000
        vo_poses.add(t_s, got.pose, got.ok, got.reinit)
        true_poses.add(t_s, truth.pose, True, i == 0)
        if i % every:
            continue
        for o in truth.objects:
            if not usable(o, rig) or o.xyz is None:
                continue
            t0 = time.process_time()
            m = measure(gl, gr, rig, o.box)
            cpu["measure_ms"] += (time.process_time() - t0) * 1000
            cpu["boxes"] += 1
            if isinstance(m, Measured):
                measured.setdefault(o.id, []).append(View(t_s, m.xyz, m.length_m,
                                                          m.length_sd_m))
                true.setdefault(o.id, []).append(View(t_s, o.xyz, o.length_m, 0.0))
    return measured, true, vo_poses, true_poses, cpu


def score(seqs: list[tuple[dict[int, list[View]], dict[int, list[View]], RigPoses, RigPoses]],
          moving: bool, min_speed: float) -> dict[str, Any]:
    """Per track: speed with VO's poses (and, rig moving, without), against the truth."""
    with_vo: list[float] = []
    without: list[float] = []
    no_speed = 0
    for measured, true, vo_poses, true_poses in seqs:
        for aid, views in measured.items():
            if len(views) < MIN_SPEED_VIEWS:
                continue
            want = aggregate(true[aid], true_poses).get("speed_m_s")
            if want is None or want < min_speed:
                continue
            got = aggregate(views, vo_poses).get("speed_m_s")
            if got is None:
                no_speed += 1
            else:
                with_vo.append(abs(got - want) / want)
            raw = aggregate(views).get("speed_m_s")  # camera frame: the rig's motion kept
            if raw is not None:
                without.append(abs(raw - want) / want)

    def stats(errs: list[float]) -> dict[str, Any]:
        e = np.array(errs) * 100
        return {"tracks": len(errs),
                "median_err_pct": round(float(np.median(e)), 2) if errs else None,
                "p90_err_pct": round(float(np.percentile(e, 90)), 2) if errs else None,
                "within_10pct": round(float((e <= 10).mean()), 3) if errs else None}

    out = {"rig": "moving" if moving else "still", "vo_removed": stats(with_vo),
           "tracks_without_speed": no_speed}
    if moving:
        out["rig_motion_kept"] = stats(without)
    return out


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="100 pairs a sequence, one seed")
    ap.add_argument("--seeds", default=",".join(map(str, HELD_OUT_SEEDS)))
    ap.add_argument("--pairs", type=int, default=300, help="pairs per sequence")
    ap.add_argument("--rate", type=float, default=10.0, help="pairs per second")
    ap.add_argument("--every", type=int, default=2, help="measure every N-th pair")
    ap.add_argument("--min-speed", type=float, default=0.02, help="m/s, true speed scored")
    args = ap.parse_args()
    if args.quick:
        args.pairs, args.seeds = 100, args.seeds.split(",")[0]
    cv2.setNumThreads(1)  # one core, as a pool worker runs
    seeds = [int(s) for s in args.seeds.split(",")]
    result: dict[str, Any] = {"seeds": seeds, "pairs_per_sequence": args.pairs,
                              "rate_hz": args.rate, "measured_every": args.every,
                              "min_true_speed_m_s": args.min_speed,
                              "rig": "640x360, hfov 70 deg, baseline 0.12 m"}
    for moving in (False, True):
        seqs = []
        cpu = {"vo_ms": 0.0, "measure_ms": 0.0, "boxes": 0.0}
        for seed in seeds:
            views, true, vo_poses, true_poses, c = run_sequence(seed, moving, args.pairs,
                                                                args.rate, args.every)
            seqs.append((views, true, vo_poses, true_poses))
            cpu = {k: cpu[k] + c[k] for k in cpu}
        key = "moving" if moving else "still"
        result[key] = score(seqs, moving, args.min_speed)
        result[key]["vo_ms_per_pair"] = round(cpu["vo_ms"] / (args.pairs * len(seeds)), 2)
        result[key]["measure_ms_per_box"] = round(cpu["measure_ms"] / max(cpu["boxes"], 1), 3)
        h.log("speed", f"rig {key} done")
    tables = [table(result)]
    h.write(args.out, "speed", tables)
    print(h.markdown(tables))


def table(result: dict[str, Any]) -> h.Result:
    """Speed errors per rig, with VO's motion removed and (rig moving) kept."""
    t = h.Result("speed", f"Track speed over the ground against the truth ({result['rig']}, "
                 f"seeds {','.join(map(str, result['seeds']))}, {result['pairs_per_sequence']} "
                 f"pairs at {result['rate_hz']:g} pairs/s)", key="rig, frame", data=result,
                 notes=[f"Tracks of a true speed of at least {result['min_true_speed_m_s']} m/s; "
                        "error: |measured - true| / true. VO ms per pair and measurement ms "
                        "per box: CPU in this run."])
    for rig in ("still", "moving"):
        r = result[rig]
        for label, key in (("VO removed", "vo_removed"), ("rig motion kept", "rig_motion_kept")):
            if key not in r:
                continue
            s = r[key]
            t.add(f"{rig}, {label}", tracks=h.Figure(s["tracks"]), **{
                "median error": h.Figure(s["median_err_pct"], "%"),
                "p90 error": h.Figure(s["p90_err_pct"], "%"),
                "within 10 %": h.Figure(s["within_10pct"], digits=3),
                "no speed": h.Figure(r["tracks_without_speed"] if key == "vo_removed" else None),
                "VO": h.Figure(r["vo_ms_per_pair"], "ms/pair"),
                "measurement": h.Figure(r["measure_ms_per_box"], "ms/box", digits=3)})
    return t


if __name__ == "__main__":
    main()
