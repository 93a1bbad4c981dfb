"""Benchmark of per-detection stereo measurement on the synthetic world, against its truth.

Boxes come from the truth (animals at most 10 % hidden, wholly inside the image), so the
numbers are the measurement's alone, not the detector's. Per range bin: how many boxes were
measured, median absolute length and range errors (%), and honesty (the share of true values
within 2 sd). Each matcher with the floor's plane (fitted once per pair, as the detector
does) and without. Also CPU ms per detection (its box, and its share of its pair's floor)
beside the packaged detector's process() per pair, in the same run.
Seeds given with --seeds; the defaults are held out (never used while developing).

Writes measure.json and measure.md into --out and prints the tables.
Usage: python -m benchmarks.measure [--quick] [--seeds S,S] [--pairs 12] [--step 15]
       [--matcher ncc|sgbm|both] [--out bench-results]     (--quick: 4 pairs, two seeds)
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from benchmarks import harness as h
from trapflow.calibration.camera import StereoRig
from trapflow.measure.stereo import Matcher, Measured, MeasureParams, measure, pair_floor
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.wire.messages import TruthObject

HELD_OUT_SEEDS = (9101, 9102, 9103, 9104, 9105, 9106)
BINS = ((0.5, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 2.5), (2.5, 4.0))
MAX_OCCLUDED = 0.1
Detect = Callable[[np.ndarray, np.ndarray, int], object]


def usable(o: TruthObject, rig: StereoRig) -> bool:
    """An animal seen whole: little hidden, its box clear of the image's edges."""
    x1, y1, x2, y2 = o.box
    return (o.label in ("crab", "scallop") and o.occluded <= MAX_OCCLUDED and o.xyz is not None
            and x1 > 1 and y1 > 1 and x2 < rig.width - 1 and y2 < rig.height - 1)


def collect(seeds: list[int], pairs: int, step: int, matcher: Matcher, params: MeasureParams,
            floor: bool) -> tuple[list[dict[str, Any]], list[float], list[float]]:
    """One row per usable truth box: truth, measurement or reason; CPU ms per detection (its
    call, and its share of the pair's floor fit); and the detector's CPU ms per pair on the
    same pairs, interleaved, so that the ratio of the two comes from one run."""
    rig = StereoRig.from_fov(640, 360, 70.0, 0.12)
    detect = detector(rig)
    rows: list[dict[str, Any]] = []
    cpu: list[float] = []
    det_ms: list[float] = []
    for seed in seeds:
        for moving in (False, True):
            opts = SynthOptions(density=2.0, empty_fraction=0.0, episode_s=12.0)
            world = World(rig, seed=seed, moving=moving, rate_hz=5.0, options=opts)
            for i in range(0, pairs * step, step):
                left, right, truth = world.render(i)
                gl = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)
                gr = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)
                boxes = [o for o in truth.objects if usable(o, rig)]
                if not boxes:
                    continue
                if detect is not None:
                    t0 = time.process_time()
                    detect(left, right, i)
                    det_ms.append((time.process_time() - t0) * 1000)
                t0 = time.process_time()
                plane = pair_floor(gl, gr, rig, params) if floor else None
                share = (time.process_time() - t0) * 1000 / len(boxes)
                for o in boxes:
                    t0 = time.process_time()
                    m = measure(gl, gr, rig, o.box, params, matcher, plane)
                    cpu.append((time.process_time() - t0) * 1000 + share)
                    assert o.xyz is not None
                    row: dict[str, Any] = {"seed": seed, "moving": moving, "pair": i,
                                           "label": o.label, "range": math.dist(o.xyz, (0, 0, 0)),
                                           "length": o.length_m}
                    if isinstance(m, Measured):
                        row.update(m_range=m.range_m, sd_range=m.range_sd_m, m_length=m.length_m,
                                   sd_length=m.length_sd_m, method=m.length_method)
                    else:
                        row["reason"] = m.reason
                    rows.append(row)
    return rows, cpu, det_ms


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per range bin and overall: counts, median errors (%), honesty (within 2 sd)."""
    out: dict[str, Any] = {}
    for lo, hi in ((*b,) for b in (*BINS, (0.5, 2.5))):
        sel = [r for r in rows if lo <= r["range"] < hi]
        got = [r for r in sel if "m_range" in r]
        key = f"{lo}-{hi} m" if (lo, hi) != (0.5, 2.5) else "all 0.5-2.5 m"
        if not sel:
            continue
        le = np.array([abs(r["m_length"] - r["length"]) / r["length"] for r in got])
        re = np.array([abs(r["m_range"] - r["range"]) / r["range"] for r in got])
        lh = np.array([abs(r["m_length"] - r["length"]) <= 2 * r["sd_length"] for r in got])
        rh = np.array([abs(r["m_range"] - r["range"]) <= 2 * r["sd_range"] for r in got])
        out[key] = {
            "boxes": len(sel), "measured": len(got),
            "length_err_median_pct": round(100 * float(np.median(le)), 2) if got else None,
            "range_err_median_pct": round(100 * float(np.median(re)), 2) if got else None,
            "length_within_2sd": round(float(lh.mean()), 3) if got else None,
            "range_within_2sd": round(float(rh.mean()), 3) if got else None,
            "methods": dict(Counter(r["method"] for r in got)),
            "reasons": dict(Counter(r["reason"] for r in sel if "reason" in r)),
        }
    return out


def detector(rig: StereoRig) -> Detect | None:
    """The packaged detector's process() on a pair, its own measuring off (so that it is the
    detector's cost alone); None where the detector or its model is not installed."""
    try:
        from trapflow_workers.common import MODELS_DIR
        from trapflow_workers.crab_detector import CrabDetector
    except ImportError:
        return None
    if not (MODELS_DIR / "crab_detector.onnx").is_file():
        return None
    from trapflow.testing.kit import make_context, make_pair

    det = CrabDetector()
    det.configure({"measure": False}, make_context(rig, pool="mono"))
    return lambda left, right, seq: det.process(make_pair(left, right, seq=seq))


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="4 pairs a sequence, two seeds")
    ap.add_argument("--seeds", default=",".join(map(str, HELD_OUT_SEEDS)))
    ap.add_argument("--pairs", type=int, default=12, help="pairs per sequence")
    ap.add_argument("--step", type=int, default=15, help="pairs apart (5 Hz)")
    ap.add_argument("--matcher", choices=("ncc", "sgbm", "both"), default="both")
    args = ap.parse_args()
    if args.quick:
        args.pairs, args.seeds = 4, ",".join(args.seeds.split(",")[:2])
    cv2.setNumThreads(1)  # one core, as a pool worker runs
    seeds = [int(s) for s in args.seeds.split(",")]
    params = MeasureParams()
    result: dict[str, Any] = {"seeds": seeds, "pairs_per_sequence": args.pairs,
                              "rig": "640x360, hfov 70 deg, baseline 0.12 m",
                              "params": {k: getattr(params, k) for k in params.__struct_fields__}}
    matchers: list[Matcher] = ["ncc", "sgbm"] if args.matcher == "both" else [args.matcher]
    for matcher in matchers:
        for floor in (True, False):
            rows, cpu, det_ms = collect(seeds, args.pairs, args.step, matcher, params, floor)
            ms = float(np.median(cpu))
            det = float(np.median(det_ms)) if det_ms else None
            key = matcher + ("" if floor else "_no_floor")
            result[key] = {"cpu_ms_per_detection_median": round(ms, 3),
                           "cpu_ms_per_detection_mean": round(float(np.mean(cpu)), 3),
                           "cpu_ms_p90": round(float(np.percentile(cpu, 90)), 3),
                           "detector_process_ms_median": round(det, 3) if det else None,
                           "cost_vs_detector": round(ms / det, 3) if det else None,
                           "bins": summarise(rows)}
            h.log("measure", f"{key} done")
    tables = results(result, [m + s for m in matchers for s in ("", "_no_floor")])
    h.write(args.out, "measure", tables)
    print(h.markdown(tables))


def results(result: dict[str, Any], keys: list[str]) -> list[h.Result]:
    """The cost of a measurement per configuration, then its errors per range bin."""
    cost = h.Result("measure", f"Stereo measurement against the truth ({result['rig']}, "
                    f"seeds {','.join(map(str, result['seeds']))})", key="matcher", data=result,
                    notes=["CPU ms per detection: its box and its share of the pair's floor "
                           "fit, median and 90th percentile; the packaged detector's "
                           "process() per pair on the same pairs, interleaved."])
    for key in keys:
        r = result[key]
        cost.add(key, **{
            "CPU per detection": h.Figure(r["cpu_ms_per_detection_median"], "ms", digits=3),
            "p90": h.Figure(r["cpu_ms_p90"], "ms", digits=3),
            "detector process()": h.Figure(r["detector_process_ms_median"], "ms", digits=1),
            "x detector": h.Figure(r["cost_vs_detector"], digits=3)})
    out = [cost]
    for key in keys:
        t = h.Result("measure", f"{key}: errors per range bin", key="range")
        for label, b in result[key]["bins"].items():
            t.add(label, boxes=h.Figure(b["boxes"]), measured=h.Figure(b["measured"]), **{
                "length error": h.Figure(b["length_err_median_pct"], "%"),
                "range error": h.Figure(b["range_err_median_pct"], "%"),
                "length within 2 sd": h.Figure(b["length_within_2sd"], digits=3),
                "range within 2 sd": h.Figure(b["range_within_2sd"], digits=3)})
        out.append(t)
    return out


if __name__ == "__main__":
    main()
