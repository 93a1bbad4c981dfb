"""Benchmark of the four algorithm plugins: processing time per pair, alone and all together,
VO speed at 1280x720 and 640x480 on one core, and VO drift over a 30 m path, all on frames of
the moving synthetic world (trapflow.synth; --drift-world testkit: the older flat test floor).

Writes algorithms.json and algorithms.md into --out. Uses the packaged demo
models when present, else tiny stand-in ONNX models (then only pre/post-processing is timed).
"""

from __future__ import annotations

import multiprocessing as mp
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from trapflow_workers.apriltags import AprilTags
from trapflow_workers.common import MODELS_DIR
from trapflow_workers.crab_detector import VARIANTS, CrabDetector
from trapflow_workers.scene_classifier import SceneClassifier
from trapflow_workers.stereo_vo import StereoOdometry

from benchmarks import harness as h
from tests.kits.scenes import FloorWorld, circle_path
from trapflow.calibration.camera import StereoRig
from trapflow.plugin import Worker
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.testing.kit import make_context, make_pair
from trapflow.testing.vo_metrics import as_4x4, drift_percent, end_drift_percent, path_length

RATE_HZ = 15.0

PLUGINS: dict[str, type[Worker]] = {
    "mono": CrabDetector,
    "stereo": SceneClassifier,
    "vo": StereoOdometry,
    "tags": AprilTags,
}


def _models(tmp: Path) -> tuple[dict[str, dict[str, Any]], dict[str, str]]:
    """Params per pool and where each model came from."""
    from tests.kits.onnx_models import colour_classifier, constant_detector, yolo_tensor

    params: dict[str, dict[str, Any]] = {"mono": {}, "stereo": {}, "vo": {}, "tags": {}}
    origin = {"mono": "demo model", "stereo": "demo model", "vo": "-", "tags": "-"}
    if not (MODELS_DIR / "crab_detector.onnx").is_file():
        out = yolo_tensor("yolov8", [(100, 100, 200, 200)], [0], [0.9], 1, (640, 640), n=8400)
        params["mono"]["model"] = str(constant_detector(tmp / "det.onnx", out, (640, 640)))
        origin["mono"] = "stand-in (decoding only)"
    if not (MODELS_DIR / "scene_classifier.onnx").is_file():
        params["stereo"]["model"] = str(colour_classifier(tmp / "clf.onnx", (224, 224)))
        origin["stereo"] = "stand-in (tiny)"
    return params, origin


def _frames(name: str, rig: StereoRig, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """n consecutive pairs of the moving world (with tags on the floor for the tag detector)."""
    opts = SynthOptions(tags=8 if name == "tags" else 0, density=1.5)
    world = World(rig, seed=1, moving=True, rate_hz=RATE_HZ, options=opts)
    return [world.render(i)[:2] for i in range(n)]


def _time(
    name: str, rig: StereoRig, params: dict[str, Any], n: int, start: Any = None
) -> dict[str, float]:
    cv2.setNumThreads(1)
    frames = _frames(name, rig, n)
    worker = PLUGINS[name]()
    worker.configure(params, make_context(rig, pool=name))
    if start is not None:
        start.wait()
    times = []
    t0 = time.perf_counter()
    for i, (left, right) in enumerate(frames):
        t = time.perf_counter()
        worker.process(make_pair(left, right, seq=i))
        times.append(time.perf_counter() - t)
    wall = time.perf_counter() - t0
    ms = np.array(times) * 1000
    return {
        "frames": n,
        "mean_ms": float(ms.mean()),
        "p95_ms": float(np.percentile(ms, 95)),
        "pairs_per_s": n / wall,
    }


def _detector_variants(rig: StereoRig, params: dict[str, Any], n: int,
                       repeats: int) -> dict[str, Any]:
    """The detector in one process, each pair through both sides of each comparison in turn
    (so load on the machine falls on both alike): process() with the fp32 and the int8 demo
    model; the input tensor by the preallocated Preprocessor and by allocate_tensor (new
    arrays at every step); a JPEG pair decoded whole and at the detector's DCT reduction."""
    from trapflow_workers.yolo_preprocess import allocate_tensor

    from trapflow.pools.pair_path import decode_pair
    from trapflow.wire import jpeg
    from trapflow.wire.messages import StereoPair

    cv2.setNumThreads(1)
    frames = [left for left, _ in _frames("mono", rig, n)]
    ctx = make_context(rig, pool="mono")
    dets: dict[str, CrabDetector] = {}
    for variant in ("fp32", "int8"):
        if variant == "int8" and (params.get("model") or not (MODELS_DIR / VARIANTS["int8"])
                                  .is_file()):
            continue  # stand-in models, or no int8 file: fp32 only
        det = CrabDetector()
        det.configure({**params, "variant": variant}, ctx)
        dets[variant] = det
    fp32 = dets["fp32"]
    pre = fp32.preprocess
    spec = (pre.input_hw, pre.placement, pre.fill, pre.rgb, pre.scale)
    header = StereoPair(seq=0, t_wall_ns=0, t_mono_ns=0, t_left_ns=0, t_right_ns=0, skew_ns=0,
                        encoding="jpeg", width=rig.width, height=rig.height)
    jpegs = [jpeg.encode(f, 90) for f in frames]
    whole = Worker()  # a plugin that declares no max_size: its JPEG pair is decoded whole

    def run(fn: Any, i: int) -> float:
        t = time.process_time()
        fn(i)
        return (time.process_time() - t) * 1000

    cases: dict[str, Any] = {
        "process fp32": lambda i: fp32.process(make_pair(frames[i], seq=i)),
        "preprocess preallocated": lambda i: pre(frames[i]),
        "preprocess allocating": lambda i: allocate_tensor(frames[i], *spec),
        "jpeg pair decode whole": lambda i: decode_pair(whole, header, jpegs[i], jpegs[i]),
        "jpeg pair decode reduced": lambda i: decode_pair(fp32, header, jpegs[i], jpegs[i]),
    }
    if "int8" in dets:
        int8 = dets["int8"]
        cases["process int8"] = lambda i: int8.process(make_pair(frames[i], seq=i))
    for fn in cases.values():  # warm-up
        fn(0)
    ms: dict[str, list[float]] = {k: [] for k in cases}
    for _ in range(repeats):
        for i in range(n):
            for k, fn in cases.items():
                ms[k].append(run(fn, i))
    med = {k: float(np.median(v)) for k, v in ms.items()}
    out: dict[str, Any] = {"ms_median": med, "ms_mean": {k: float(np.mean(v))
                                                         for k, v in ms.items()},
                           "pairs": n, "repeats": repeats,
                           "reduction": jpeg.scale_for((rig.width, rig.height), fp32.max_size),
                           "ratios": {
        "preallocated / allocating preprocessing":
            med["preprocess preallocated"] / med["preprocess allocating"],
        "reduced / whole JPEG pair decode":
            med["jpeg pair decode reduced"] / med["jpeg pair decode whole"]}}
    if "process int8" in med:
        out["ratios"]["int8 / fp32 process()"] = med["process int8"] / med["process fp32"]
    return out


def _variants(v: dict[str, Any], size: str) -> list[h.Result]:
    """The detector's cases at one size, and their ratios in the same run."""
    cases = h.Result("algorithms", f"Detector variants at {size}", key="case", notes=[
        f"One process, CPU ms per pair (median of {v['pairs']} "
        f"pairs x {v['repeats']}, each pair through every case in turn)."])
    for k, m in v["ms_median"].items():
        cases.add(k, median=h.Figure(m, "ms"), mean=h.Figure(v["ms_mean"][k], "ms"))
    ratios = h.Result("algorithms", key="ratio, same run")
    for k, r in v["ratios"].items():
        ratios.add(k, **{"x": h.Figure(round(r, 4))})
    return [cases, ratios]


def _detector_only(out: Path, pairs: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        params, origin = _models(Path(tmp))
        variants = {f"{w}x{ht}": _detector_variants(StereoRig.from_fov(w, ht, 70.0, 0.12),
                                                    params["mono"], pairs, 3)
                    for w, ht in ((1280, 720), (1920, 1080))}
    results = [t for k, v in variants.items() for t in _variants(v, k)]
    results[0].data = {"detector_variants": variants, "models": origin}
    h.write(out, "detector_variants", results)
    print(h.markdown(results))


def _together(rig: StereoRig, params: dict[str, dict[str, Any]], n: int) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    start = ctx.Manager().Barrier(len(PLUGINS))
    with ctx.Pool(len(PLUGINS)) as pool:
        jobs = {k: pool.apply_async(_time, (k, rig, params[k], n, start)) for k in PLUGINS}
        return {k: j.get(timeout=600) for k, j in jobs.items()}


def _drift_testkit(
    rig: StereoRig, length_m: float, steps: int
) -> tuple[list[np.ndarray], list[np.ndarray], int]:
    radius = length_m / 6.0
    world = FloorWorld.square(rig, 2 * radius + 5, res_m=0.003, seed=2)
    vo = StereoOdometry()
    vo.configure({}, make_context(rig, pool="vo"))
    truth, est, ok = [], [], 0
    for i, p in enumerate(circle_path(length_m, steps, radius)):
        res = vo.process(make_pair(*world.render(p), seq=i))
        truth.append(p)
        est.append(as_4x4(res.pose))
        ok += res.ok
    return truth, est, ok


def _drift_world(
    rig: StereoRig, length_m: float, speed: float
) -> tuple[list[np.ndarray], list[np.ndarray], int]:
    """Render and track until the rig has travelled length_m (true path length)."""
    world = World(rig, seed=4, moving=True, rate_hz=RATE_HZ, options=SynthOptions(speed=speed))
    vo = StereoOdometry()
    vo.configure({}, make_context(rig, pool="vo"))
    truth, est, ok, travelled = [], [], 0, 0.0
    i = 0
    while travelled < length_m:
        left, right, t = world.render(i)
        res = vo.process(make_pair(left, right, seq=i))
        truth.append(as_4x4(t.pose))
        est.append(as_4x4(res.pose))
        ok += res.ok
        if i > 0:
            travelled += float(np.linalg.norm(truth[-1][:3, 3] - truth[-2][:3, 3]))
        i += 1
    return truth, est, ok


def _drift(
    rig: StereoRig, source: str, length_m: float, steps: int, speed: float
) -> dict[str, Any]:
    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    if source == "world":
        truth, est, ok = _drift_world(rig, length_m, speed)
    else:
        truth, est, ok = _drift_testkit(rig, length_m, steps)
    segments = [length_m * f for f in (0.2, 0.4, 0.6, 0.8)]
    return {
        "source": source,
        "speed_m_s": speed if source == "world" else None,
        "path_m": float(path_length(truth)[-1]),
        "pairs": len(truth),
        "ok": ok,
        "segments_m": segments,
        "segment_drift_pct": drift_percent(truth, est, segments),
        "end_drift_pct": end_drift_percent(truth, est),
        "wall_s": time.perf_counter() - t0,
    }


def _table(rows: list[tuple[str, str, dict[str, float]]]) -> h.Result:
    t = h.Result("algorithms", "Algorithms: process() per pair", key="algorithm, run")
    for name, run, r in rows:
        t.add(f"{name}, {run}", **{"analysed frames": h.Figure(r["frames"]),
                                   "mean": h.Figure(r["mean_ms"], "ms", digits=1),
                                   "p95": h.Figure(r["p95_ms"], "ms", digits=1),
                                   "pairs/s": h.Figure(r["pairs_per_s"], digits=1)})
    return t


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="30 pairs a run, 10 for the variants")
    ap.add_argument("--frames", type=int, default=120, help="pairs per algorithm run")
    ap.add_argument("--path-m", type=float, default=30.0, help="VO drift path length")
    ap.add_argument(
        "--drift-world",
        choices=("world", "testkit"),
        default="world",
        help="drift on the moving synthetic world, or the flat testkit floor (a circle)",
    )
    ap.add_argument(
        "--speed", type=float, default=0.5, help="rig speed in m/s on the world (15 pairs/s)"
    )
    ap.add_argument("--variant-pairs", type=int, default=40,
                    help="pairs for the detector variants (fp32/int8, preprocessing, decode)")
    ap.add_argument("--detector-only", action="store_true",
                    help="only the detector variants; writes detector_variants.json and .md")
    ap.add_argument("--steps", type=int, default=600, help="pairs along the testkit path")
    args = ap.parse_args()
    if args.quick:
        args.frames, args.variant_pairs, args.steps = 30, 10, 150
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    if args.detector_only:
        _detector_only(out, args.variant_pairs)
        return
    hd, vga = StereoRig.from_fov(1280, 720, 70.0, 0.12), StereoRig.from_fov(640, 480, 70.0, 0.12)
    with tempfile.TemporaryDirectory() as tmp:
        params, origin = _models(Path(tmp))
        alone = {k: _time(k, hd, params[k], args.frames) for k in PLUGINS}
        vo_vga = _time("vo", vga, {}, args.frames)
        together = _together(hd, params, args.frames)
        variants = {f"{r.width}x{r.height}": _detector_variants(r, params["mono"],
                                                                  args.variant_pairs, 3)
                    for r in (hd, StereoRig.from_fov(1920, 1080, 70.0, 0.12))}
    drift = _drift(hd, args.drift_world, args.path_m, args.steps, args.speed)
    rows = [(k, "alone 1280x720", alone[k]) for k in PLUGINS]
    rows.append(("vo", "alone 640x480", vo_vga))
    rows += [(k, "all together 1280x720", together[k]) for k in PLUGINS]
    report = {
        "alone": alone,
        "vo_640x480": vo_vga,
        "together": together,
        "drift": drift,
        "detector_variants": variants,
        "models": origin,
        "threads": 1,
        "frames_from": f"moving synthetic world, {RATE_HZ:g} pairs/s",
    }
    where = (
        f"moving synthetic world at {args.speed:g} m/s"
        if args.drift_world == "world"
        else "flat testkit floor"
    )
    seg_m = ", ".join(f"{v:g}" for v in drift["segments_m"])
    main_t = _table(rows)
    main_t.data = report
    main_t.notes = [
        f"Models: {', '.join(f'{k}: {v}' for k, v in origin.items())}. One OpenCV / "
        "onnxruntime thread per process; frames of the moving synthetic world.",
        f"VO drift over a {drift['path_m']:.1f} m path of the {where} ({drift['pairs']} pairs "
        f"at 1280x720, {drift['ok']} ok): {drift['segment_drift_pct']:.3f} % (KITTI-style "
        f"segment metric, segments of {seg_m} m), {drift['end_drift_pct']:.3f} % at the end."]
    results = [main_t, *(t for k, v in variants.items() for t in _variants(v, k))]
    h.write(out, "algorithms", results)
    print(h.markdown(results))


if __name__ == "__main__":
    main()
