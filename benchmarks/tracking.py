"""Scores trapflow's tracker on synthetic sequences: HOTA (TrackEval), IDF1 and MOTA
(py-motmetrics), against a greedy-IoU baseline and Roboflow's ByteTrack (`trackers`).

Ground truth: the synthetic world's labelled objects (TruthObject.id is the animal's id).
Detections: derived from truth with a seeded rng (boxes jittered, some dropped, more so
when occluded, some given a low confidence or a wrong label, false positives added), at
full rate and with the detector seeing one pair in three. Scores count only the pairs the
detector saw (no tracker can answer for the others). Development seeds (1001-1016) tune
the defaults (benchmarks/tune_tracking.py); held-out seeds (2001-2006) are reported. Both
trackers get the same frame rate and each pair's capture time. Writes tracking.json and
tracking.md into --out (default bench-results) and prints the tables.

--live adds the tracker inside the pipeline: held-out seeds rendered by `trapflow dataset
synth` are run through `trapflow start --source images:DIR` (the mono pool alone, fifo for
every pair, then `latest` with the detector slowed so that it sees about one pair in three);
the run's tracked lines (frame = seq + 1) are scored against the dataset's gt/gt.txt over
the pairs the detector saw, beside the other trackers on the run's own detections.

--crocea adds the real fish tracks of realdata 08 (detections made from them, see
benchmarks/tracking_realdata.py), per video beside ByteTrack, with MaxN per class three ways
(the truth's, confirmed tracks at one capture time, confident detections in one frame; --max-n
adds the same on the synthetic sequences); --scorer-check scores a published tracker's
output on TUD (realdata 08b) beside its published scores.

    python -m benchmarks.tracking [--quick] [--split dev|held-out|both|none] [--frames N]
                                  [--live [--live-seeds S,S] [--live-frames N]]
                                  [--crocea [--crocea-seqs N,N] [--crocea-fps F]]
                                  [--scorer-check] [--max-n] [--out DIR]
    (--quick: 150 pairs a sequence, 60 a live one)

Needs the test extra (motmetrics) and, bench only, TrackEval and Roboflow's trackers:
`pip install supervision && pip install --no-deps trackeval trackers` (--no-deps: both
ask for opencv-python, a second OpenCV beside opencv-python-headless; they run on either).
Without trackers the ByteTrack rows are left out.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import yaml

from benchmarks import harness as h
from benchmarks.tracking_realdata import (
    CROCEA_FPS,
    RealSequence,
    crocea_sequences,
    scorer_check,
)
from trapflow.calibration.camera import StereoRig
from trapflow.synth.dataset import labelled
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.tracking.assign import iou_matrix
from trapflow.tracking.motformat import MotRow, read_mot, track_rows
from trapflow.tracking.relink import RelinkConfig
from trapflow.tracking.tracker import TrackerConfig
from trapflow.wire.messages import Truth

FPS = 15.0
WIDTH, HEIGHT = 640, 360
# Development seeds (tuning, benchmarks/tune_tracking.py); the held-out ones are never tuned on.
DEV_SEEDS = tuple(range(1001, 1017))
HELD_OUT_SEEDS = (2001, 2002, 2003, 2004, 2005, 2006)
# A busy floor: more animals per scene and few empty scenes, so that tracks cross.
OPTIONS = SynthOptions(density=3.0, empty_fraction=0.1, episode_s=20.0)
RATES = {"full": 1, "third": 3}
LABELS = ("crab", "scallop", "tag")

# How the fake detector errs.
P_DROP = 0.08  # a visible object missed
P_DROP_OCCLUDED = 0.5  # added, times the hidden fraction
P_LOW = 0.2  # a found object given a low confidence (ByteTrack's second stage is for these)
P_WRONG_LABEL = 0.05
JITTER = 0.04  # box centre and size noise, in box sides
FALSE_PER_PAIR = 0.4  # mean false positives per pair


@dataclass(frozen=True)
class SynthSequence:
    """One synthetic sequence: truth rows and detection rows per rate."""

    name: str
    gt: list[MotRow]
    dets: dict[str, list[MotRow]]


def render_truth(seed: int, frames: int, moving: bool) -> list[Truth]:
    rig = StereoRig.from_fov(WIDTH, HEIGHT, 70.0, 0.12)
    world = World(rig, seed=seed, moving=moving, rate_hz=FPS, options=OPTIONS)
    return [world.render(i)[2] for i in range(frames)]


def gt_rows(truths: list[Truth]) -> list[MotRow]:
    out = []
    for i, tr in enumerate(truths):
        for o in labelled(tr):
            if o.label == "tag":  # AprilTag ids would collide with the animals' (none here)
                continue
            x1, y1, x2, y2 = o.box
            out.append(MotRow(frame=i + 1, id=o.id, x=x1, y=y1, w=x2 - x1, h=y2 - y1,
                              conf=1.0, cls=LABELS.index(o.label)))
    return out


def fake_detections(truths: list[Truth], seed: int) -> list[MotRow]:
    """Detector output for every pair (seeded), in MOT rows with id -1."""
    rng = np.random.default_rng([seed, 77])
    out = []
    for i, tr in enumerate(truths):
        for o in labelled(tr):
            if rng.random() < P_DROP + P_DROP_OCCLUDED * o.occluded:
                continue
            x1, y1, x2, y2 = o.box
            w, h = x2 - x1, y2 - y1
            cx = (x1 + x2) / 2 + rng.normal(0, JITTER) * w
            cy = (y1 + y2) / 2 + rng.normal(0, JITTER) * h
            w *= float(np.exp(rng.normal(0, JITTER)))
            h *= float(np.exp(rng.normal(0, JITTER)))
            conf = rng.uniform(0.15, 0.5) if rng.random() < P_LOW else rng.uniform(0.5, 0.95)
            cls = LABELS.index(o.label)
            if rng.random() < P_WRONG_LABEL:
                cls = int(rng.integers(len(LABELS)))
            out.append(MotRow(frame=i + 1, id=-1, x=cx - w / 2, y=cy - h / 2, w=w, h=h,
                              conf=float(conf), cls=cls))
        for _ in range(rng.poisson(FALSE_PER_PAIR)):
            w = rng.uniform(15, 70)
            h = w * rng.uniform(0.6, 1.4)
            x, y = rng.uniform(0, WIDTH - w), rng.uniform(0, HEIGHT - h)
            conf = rng.uniform(0.1, 0.45) if rng.random() < 0.8 else rng.uniform(0.5, 0.7)
            out.append(MotRow(frame=i + 1, id=-1, x=x, y=y, w=w, h=h, conf=float(conf),
                              cls=int(rng.integers(len(LABELS)))))
    return out


def make_sequence(seed: int, frames: int) -> SynthSequence:
    moving = seed % 2 == 0  # half the sequences from a moving rig
    truths = render_truth(seed, frames, moving)
    dets = fake_detections(truths, seed)
    by_rate = {name: [r for r in dets if (r.frame - 1) % step == 0]
               for name, step in RATES.items()}
    return SynthSequence(name=f"seed{seed}{'-moving' if moving else ''}", gt=gt_rows(truths),
                     dets=by_rate)


# --- trackers under test: detection rows -> track rows --------------------------------


def run_trapflow(config: TrackerConfig, fps: float = FPS, relink: RelinkConfig | None = None
                 ) -> Callable[[list[MotRow]], list[MotRow]]:
    return lambda dets: track_rows(dets, fps, config, relink=relink)


def run_greedy(dets: list[MotRow], iou_min: float = 0.3, conf_min: float = 0.3,
               max_gap_s: float = 1.5) -> list[MotRow]:
    """The baseline: each detection to the track whose last box overlaps it most, greedily;
    no motion model, every track reported from its first box."""
    tracks: dict[int, tuple[float, np.ndarray]] = {}  # id -> (last time, last box)
    next_id, out = 1, []
    frames: dict[int, list[MotRow]] = {}
    for r in dets:
        if r.conf >= conf_min:
            frames.setdefault(r.frame, []).append(r)
    for frame in sorted(frames):
        t = (frame - 1) / FPS
        tracks = {k: v for k, v in tracks.items() if t - v[0] <= max_gap_s}
        rows = frames[frame]
        boxes = np.array([[r.x, r.y, r.x + r.w, r.y + r.h] for r in rows])
        ids = list(tracks)
        iou = iou_matrix(np.array([tracks[k][1] for k in ids]).reshape(-1, 4), boxes)
        taken_t: set[int] = set()
        taken_d: set[int] = set()
        for flat in np.argsort(-iou, axis=None):
            a, b = divmod(int(flat), len(rows))
            if iou[a, b] < iou_min:
                break
            if a in taken_t or b in taken_d:
                continue
            taken_t.add(a)
            taken_d.add(b)
            tracks[ids[a]] = (t, boxes[b])
            out.append(MotRow(**{**_fields(rows[b]), "id": ids[a]}))
        for b, r in enumerate(rows):
            if b not in taken_d:
                tracks[next_id] = (t, boxes[b])
                out.append(MotRow(**{**_fields(r), "id": next_id}))
                next_id += 1
    return out


def _fields(r: MotRow) -> dict[str, Any]:
    return {f: getattr(r, f) for f in r.__struct_fields__}


def run_bytetrack(dets: list[MotRow], tuned: bool, fps: float = FPS) -> list[MotRow]:
    """Roboflow's ByteTrack on the same rows, the frame rate set and capture times given."""
    import supervision as sv
    from trackers import ByteTrackTracker

    kw = dict(track_activation_threshold=0.5, high_conf_det_threshold=0.5,
              minimum_iou_threshold=0.2, lost_track_buffer=45) if tuned else {}
    tracker = ByteTrackTracker(frame_rate=fps, **kw)  # type: ignore[arg-type,unused-ignore]  # typed only where the package is installed
    frames: dict[int, list[MotRow]] = {}
    for r in dets:
        frames.setdefault(r.frame, []).append(r)
    out = []
    for frame in sorted(frames):
        rows = frames[frame]
        d = sv.Detections(xyxy=np.array([[r.x, r.y, r.x + r.w, r.y + r.h] for r in rows]),
                          confidence=np.array([r.conf for r in rows]),
                          class_id=np.array([max(r.cls, 0) for r in rows]))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = tracker.update(d, timestamp=(frame - 1) / fps)
        assert res.tracker_id is not None and res.confidence is not None, "tracked boxes"
        for box, tid, conf in zip(res.xyxy, res.tracker_id, res.confidence, strict=True):
            if tid >= 0:
                x1, y1, x2, y2 = (float(v) for v in box)
                out.append(MotRow(frame=frame, id=int(tid), x=x1, y=y1, w=x2 - x1, h=y2 - y1,
                                  conf=float(conf)))
    return out


# --- scoring ---------------------------------------------------------------------------


def _by_frame(rows: Sequence[MotRow]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    acc: dict[int, list[MotRow]] = {}
    for r in rows:
        acc.setdefault(r.frame, []).append(r)
    return {f: (np.array([r.id for r in rs]),
                np.array([[r.x, r.y, r.x + r.w, r.y + r.h] for r in rs])) for f, rs in acc.items()}


def score(gt: list[MotRow], hyp: list[MotRow], frames: list[int]) -> dict[str, float]:
    """HOTA (TrackEval), IDF1, MOTA, ID switches (py-motmetrics) over the given frames."""
    import motmetrics as mm
    from trackeval.metrics import HOTA

    g, hy = _by_frame(gt), _by_frame(hyp)
    empty = (np.zeros(0, int), np.zeros((0, 4)))
    acc = mm.MOTAccumulator(auto_id=False)
    gid = {k: i for i, k in enumerate(sorted({r.id for r in gt}))}
    hid = {k: i for i, k in enumerate(sorted({r.id for r in hyp}))}
    gt_ids: list[np.ndarray] = []
    tracker_ids: list[np.ndarray] = []
    sims: list[np.ndarray] = []
    for f in frames:
        gi, gb = g.get(f, empty)
        hi, hb = hy.get(f, empty)
        iou = iou_matrix(gb, hb)
        acc.update(list(gi), list(hi), np.where(iou >= 0.5, 1.0 - iou, np.nan), frameid=f)
        gt_ids.append(np.array([gid[k] for k in gi], int))
        tracker_ids.append(np.array([hid[k] for k in hi], int))
        sims.append(iou)
    data: dict[str, list[np.ndarray] | int] = {
        "gt_ids": gt_ids, "tracker_ids": tracker_ids, "similarity_scores": sims,
        "num_gt_ids": len(gid), "num_tracker_ids": len(hid), "num_timesteps": len(frames),
        "num_gt_dets": sum(len(x) for x in gt_ids),
        "num_tracker_dets": sum(len(x) for x in tracker_ids)}
    summary = mm.metrics.create().compute(acc, metrics=["idf1", "mota", "num_switches",
                                                   "num_false_positives", "num_misses",
                                                   "num_fragmentations"],
                                          name="s")
    hota = HOTA().eval_sequence(data)
    return {"HOTA": float(np.mean(hota["HOTA"])), "DetA": float(np.mean(hota["DetA"])),
            "AssA": float(np.mean(hota["AssA"])), "IDF1": float(summary["idf1"].iloc[0]),
            "MOTA": float(summary["mota"].iloc[0]), "IDSW": int(summary["num_switches"].iloc[0]),
            "FP": int(summary["num_false_positives"].iloc[0]),
            "FN": int(summary["num_misses"].iloc[0]),
            "FRAG": int(summary["num_fragmentations"].iloc[0]),
            "gt_dets": int(data["num_gt_dets"]), "gt_ids": len(gid)}  # type: ignore[arg-type]


def evaluate(seqs: list[SynthSequence], trackers: dict[str, Callable[[list[MotRow]], list[MotRow]]]
             ) -> dict[str, dict[str, dict[str, float]]]:
    """Per rate and tracker: metrics pooled over sequences (weighted by ground-truth dets)."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for rate, step in RATES.items():
        out[rate] = {}
        for name, fn in trackers.items():
            per = []
            t0 = time.perf_counter()
            for s in seqs:
                last = max([r.frame for r in s.gt] + [1])
                frames = [f for f in range(1, last + 1) if (f - 1) % step == 0]
                per.append(score(s.gt, fn(s.dets[rate]), frames))
            agg = pooled(per)
            agg["seconds"] = time.perf_counter() - t0
            out[rate][name] = agg
    return out


def pooled(per: list[dict[str, float]]) -> dict[str, float]:
    """Metrics of several sequences as one: weighted by ground-truth detections, ID switches
    summed."""
    wsum = sum(p["gt_dets"] for p in per) or 1
    agg = {k: sum(p[k] * p["gt_dets"] for p in per) / wsum
           for k in ("HOTA", "DetA", "AssA", "IDF1", "MOTA")}
    agg["IDSW"] = sum(p["IDSW"] for p in per)
    return agg


def result(title: str, res: dict[str, dict[str, dict[str, float]]]) -> h.Result:
    """Per detector rate and tracker: HOTA, IDF1, MOTA, AssA, DetA (%) and ID switches."""
    r = h.Result("tracking", f"Tracking: {title}", key="rate, tracker")
    for rate, per in res.items():
        for name, m in per.items():
            r.add(f"{rate}, {name}", **{k: h.Figure(round(m[k] * 100, 2), "%", digits=1)
                                        for k in ("HOTA", "IDF1", "MOTA", "AssA", "DetA")},
                  IDSW=h.Figure(int(m["IDSW"])))
    return r


def max_n_result(title: str, mx: dict[str, dict[str, dict[str, dict[int, int]]]]) -> h.Result:
    """MaxN per class three ways, per detector rate and sequence."""
    r = h.Result("tracking", title, key="rate, sequence")
    for rate, per_seq in mx.items():
        for name, m in per_seq.items():
            r.add(f"{rate}, {name}", **{k: h.Figure(str(sorted(v.items())))
                                        for k, v in m.items()})
    return r


# --- MaxN against the truth's, and the real sets ------------------------------------------


def max_n_rows(rows: Sequence[MotRow], frames: Sequence[int]) -> dict[int, int]:
    """Per class, the most rows of one of the given frames."""
    count: dict[tuple[int, int], int] = {}
    keep = set(frames)
    for r in rows:
        if r.frame in keep:
            count[(r.cls, r.frame)] = count.get((r.cls, r.frame), 0) + 1
    out: dict[int, int] = {}
    for (cls, _f), n in count.items():
        out[cls] = max(out.get(cls, 0), n)
    return out


def max_n_tracks(tracked: Sequence[MotRow], frames: Sequence[int]) -> dict[int, int]:
    """MaxN as a live run counts it: per class (each track's majority class, as a track's
    label is), the most confirmed tracks seen at one capture time."""
    votes: dict[int, dict[int, int]] = {}
    for r in tracked:
        v = votes.setdefault(r.id, {})
        v[r.cls] = v.get(r.cls, 0) + 1
    cls_of = {tid: max(v, key=lambda c: v[c]) for tid, v in votes.items()}
    return max_n_rows([msgspec.structs.replace(r, cls=cls_of[r.id]) for r in tracked], frames)


def max_n_compare(gt: Sequence[MotRow], dets: Sequence[MotRow], tracked: Sequence[MotRow],
                  frames: Sequence[int], high: float) -> dict[str, dict[int, int]]:
    """MaxN per class three ways over the frames the detector saw: the truth's (animals in
    one frame), simultaneous confirmed tracks at one capture time (what trapflow counts),
    and confident detections (at or above `high`) in one frame."""
    return {"truth": max_n_rows(gt, frames), "tracks": max_n_tracks(tracked, frames),
            "detections": max_n_rows([r for r in dets if r.conf >= high], frames)}


def evaluate_real(seqs: Sequence[RealSequence], fps: float, with_bytetrack: bool
                  ) -> dict[str, object]:
    """Each real sequence at each detector rate: trapflow's and ByteTrack's scores, and
    MaxN three ways; then per rate the pooled scores."""
    cfg = TrackerConfig()
    trackers: dict[str, Callable[[list[MotRow]], list[MotRow]]] = {
        "trapflow": run_trapflow(cfg, fps),
        "trapflow-relink": run_trapflow(cfg, fps, RelinkConfig())}
    if with_bytetrack:
        trackers["bytetrack"] = lambda d: run_bytetrack(d, tuned=False, fps=fps)
    per: dict[str, dict[str, dict[str, object]]] = {}
    pooled_res: dict[str, dict[str, dict[str, float]]] = {}
    for rate, step in RATES.items():
        per[rate] = {}
        scores: dict[str, list[dict[str, float]]] = {name: [] for name in trackers}
        for s in seqs:
            last = max(r.frame for r in s.gt)
            frames = [f for f in range(1, last + 1) if (f - 1) % step == 0]
            dets = [r for r in s.dets if (r.frame - 1) % step == 0]
            row: dict[str, object] = {}
            for name, fn in trackers.items():
                tracked = fn(dets)
                row[name] = score(s.gt, tracked, frames)
                scores[name].append(row[name])  # type: ignore[arg-type]
                if name == "trapflow":
                    row["max_n"] = max_n_compare(s.gt, dets, tracked, frames, cfg.high)
            per[rate][s.name] = row
        pooled_res[rate] = {name: pooled(v) for name, v in scores.items()}
    return {"fps": fps, "per_sequence": per, "results": pooled_res}


def real_results(title: str, real: dict[str, object]) -> list[h.Result]:
    """Per rate and sequence: HOTA / IDF1 / ID switches of each tracker, and MaxN; then
    the pooled scores."""
    r = h.Result("tracking", f"Tracking: {title}, per sequence (HOTA / IDF1 / IDSW)",
                 key="rate, sequence")
    per: dict[str, dict[str, dict[str, object]]] = real["per_sequence"]  # type: ignore[assignment]
    for rate, seqs in per.items():
        for name, row in seqs.items():
            cells = {}
            for tr, m in row.items():
                if tr != "max_n":
                    m = dict(m)  # type: ignore[call-overload]
                    cells[tr] = h.Figure(f"{m['HOTA'] * 100:.1f} / {m['IDF1'] * 100:.1f} / "
                                         f"{int(m['IDSW'])}")
            mx: dict[str, dict[int, int]] = row["max_n"]  # type: ignore[assignment]
            cells["MaxN"] = h.Figure(" ".join(f"{k}={sorted(v.items())}"
                                              for k, v in mx.items()))
            r.add(f"{rate}, {name}", **cells)
    return [r, result(f"{title}, pooled", real["results"])]  # type: ignore[arg-type]


def synth_max_n(seqs: Sequence[SynthSequence]) -> dict[str, dict[str, dict[str, dict[int, int]]]]:
    """MaxN three ways on synthetic sequences, per rate and sequence (trapflow's tracks)."""
    cfg = TrackerConfig()
    out: dict[str, dict[str, dict[str, dict[int, int]]]] = {}
    for rate, step in RATES.items():
        out[rate] = {}
        for s in seqs:
            last = max([r.frame for r in s.gt] + [1])
            frames = [f for f in range(1, last + 1) if (f - 1) % step == 0]
            tracked = track_rows(s.dets[rate], FPS, cfg)
            out[rate][s.name] = max_n_compare(s.gt, s.dets[rate], tracked, frames, cfg.high)
    return out


# --- the tracker inside a live run --------------------------------------------------------

# Held-out seeds rendered by `trapflow dataset synth` and run through the pipeline (one still
# rig, one moving, one still); 300 pairs each keep the part to a few minutes.
LIVE_SEEDS = HELD_OUT_SEEDS[:3]
# The detector's added time per pair at `latest`: with the model's own time it then sees
# about one pair in three or fewer at 15 pairs/s (the live IDF1 test's slow detector).
SLOW_DELAY_S = 0.2
LIVE_RATES = ("full", "latest")  # fifo, every pair; `latest` with the slowed detector
REPO = Path(__file__).resolve().parent.parent


def _trapflow(args: list[str], timeout_s: float) -> None:
    """`python -m trapflow ARGS` from the repository root, in a session of its own; past
    timeout_s that session (only what this call started) is killed."""
    proc = subprocess.Popen([sys.executable, "-m", "trapflow", *args], cwd=REPO, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        _out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise SystemExit(f"trapflow {args[0]}: still running after {timeout_s:g} s, killed; "
                         "run fewer pairs (--live-frames)") from None
    if proc.returncode != 0:
        raise SystemExit(f"trapflow {args[0]} exited {proc.returncode}: {err.strip()[-2000:]}")


def live_config(path: Path, frames: int, slow: bool) -> Path:
    """A config running the mono pool alone: fifo for every pair (a finite source waits for
    no one, so the queue holds them all), or `latest` with the slowed detector. The motion
    gate is off (gate: always; mono is gated by default): the detector may see every pair."""
    from trapflow.config.schema import Config

    mono: dict[str, object] = {"count": 1, "policy": f"fifo:{frames}", "gate": "always"}
    if slow:
        mono = {"count": 1, "policy": "latest", "gate": "always",
                "plugin": "tests.integration.slow_plugins:SlowDetector",
                "params": {"delay_s": SLOW_DELAY_S}}
    pools = {**{name: {"count": 0} for name in Config().pools if name != "mono"}, "mono": mono}
    path.write_text(yaml.safe_dump({"source": {"rate_hz": FPS}, "pools": pools,
                                    "observe": {"interval_s": 3600}}))
    return path


def run_rows(results: Path) -> tuple[list[MotRow], list[MotRow], list[int]]:
    """A run's results.jsonl as MOT rows (frame = seq + 1, the source's pair index): the
    tracked detections (id = the line's track; a track's first box, null until confirmed,
    is left out), the same detections without ids, and the frames the detector saw."""
    tracked, dets, seen = [], [], set()
    for line in results.read_text().splitlines():
        d = json.loads(line)["mono_ir"]
        seen.add(d["seq"] + 1)
        if d["label"] == "none":
            continue
        x1, y1, x2, y2 = d["box"]
        row = MotRow(frame=d["seq"] + 1, id=-1, x=x1, y=y1, w=x2 - x1, h=y2 - y1,
                     conf=d["confidence"],
                     cls=LABELS.index(d["label"]) if d["label"] in LABELS else -1)
        dets.append(row)
        if d.get("track") is not None:
            tracked.append(msgspec.structs.replace(row, id=d["track"]))
    return tracked, dets, sorted(seen)


def live_sequence(seed: int, frames: int, work: Path,
                  trackers: dict[str, Callable[[list[MotRow]], list[MotRow]]]
                  ) -> dict[str, dict[str, dict[str, float]]]:
    """One held-out seed rendered, run through the pipeline at both detector rates; per rate
    the run's own tracks and each offline tracker on the run's detections, scored over the
    pairs the detector saw. "trapflow-live" is the run's own tracks; "trapflow" is
    `trapflow track` (the same tracker, offline) on the run's detections."""
    data = work / f"seed{seed}"
    opts = [a for f in ("density", "empty_fraction", "episode_s")
            for a in ("-o", f"{f}={getattr(OPTIONS, f)}")]
    _trapflow(["dataset", "synth", str(data), "--frames", str(frames), "--seed", str(seed),
               "--width", str(WIDTH), "--height", str(HEIGHT), "--rate", f"{FPS:g}", *opts,
               *(["--moving"] if seed % 2 == 0 else [])], timeout_s=600)
    gt = read_mot(data / "gt" / "gt.txt")
    out: dict[str, dict[str, dict[str, float]]] = {}
    for rate in LIVE_RATES:
        run = work / f"seed{seed}-{rate}"
        cfg = live_config(run.with_suffix(".yaml"), frames, slow=rate == "latest")
        _trapflow(["start", "--run-dir", str(run), "--config", str(cfg),
                   "--source", f"images:{data}"], timeout_s=120 + 2 * frames / FPS)
        tracked, dets, seen = run_rows(run / "results.jsonl")
        out[rate] = {"trapflow-live": score(gt, tracked, seen)}
        for name, fn in trackers.items():
            out[rate][name] = score(gt, fn(dets), seen)
        out[rate]["trapflow-live"]["pairs_seen"] = len(seen)
    return out


def live_results(seeds: Sequence[int], frames: int,
                 trackers: dict[str, Callable[[list[MotRow]], list[MotRow]]]
                 ) -> dict[str, object]:
    """Every live sequence, then per rate and tracker the pooled metrics."""
    with tempfile.TemporaryDirectory(prefix="bench-tracking-") as tmp:
        per = [live_sequence(s, frames, Path(tmp), trackers) for s in seeds]
    res = {rate: {name: pooled([p[rate][name] for p in per]) for name in per[0][rate]}
           for rate in LIVE_RATES}
    seen = {rate: [int(p[rate]["trapflow-live"]["pairs_seen"]) for p in per]
            for rate in LIVE_RATES}
    return {"seeds": list(seeds), "frames": frames, "slow_delay_s": SLOW_DELAY_S,
            "pairs_seen": seen, "results": res}


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="150 pairs a sequence, 60 a live one")
    ap.add_argument("--split", choices=("dev", "held-out", "both", "none"), default="both",
                    help="offline sequences to score (none: the live part alone)")
    ap.add_argument("--frames", type=int, default=900, help="pairs per sequence (15 per s)")
    ap.add_argument("--no-bytetrack", action="store_true")
    ap.add_argument("--crocea", action="store_true",
                    help="also score the real fish tracks (realdata 08) with made detections")
    ap.add_argument("--crocea-seqs", type=lambda t: tuple(int(x) for x in t.split(",")),
                    default=None, help="comma-separated crocea numbers (default: all 8)")
    ap.add_argument("--crocea-fps", type=float, default=CROCEA_FPS,
                    help="frame rate taken for crocea (not published with the data)")
    ap.add_argument("--scorer-check", action="store_true",
                    help="score a published tracker's output on TUD (realdata 08b)")
    ap.add_argument("--max-n", action="store_true",
                    help="also MaxN three ways on the synthetic sequences")
    ap.add_argument("--live", action="store_true",
                    help="also score the tracker inside live runs of the pipeline")
    ap.add_argument("--live-frames", type=int, default=300, help="pairs per live sequence")
    ap.add_argument("--live-seeds", type=lambda t: [int(x) for x in t.split(",")],
                    default=list(LIVE_SEEDS), help="comma-separated held-out seeds")
    args = ap.parse_args()
    if args.quick:
        args.frames, args.live_frames = 150, 60
    trackers: dict[str, Callable[[list[MotRow]], list[MotRow]]] = {
        "trapflow": run_trapflow(TrackerConfig()),
        "trapflow-relink": run_trapflow(TrackerConfig(), relink=RelinkConfig()),
        "greedy-iou": run_greedy}
    import importlib.util

    if importlib.util.find_spec("trackers") is None:
        h.log("tracking", "trackers is not installed: no ByteTrack rows")
        args.no_bytetrack = True
    if not args.no_bytetrack:
        trackers["bytetrack"] = lambda d: run_bytetrack(d, tuned=False)
        trackers["bytetrack-tuned"] = lambda d: run_bytetrack(d, tuned=True)
    splits = {"dev": DEV_SEEDS, "held-out": HELD_OUT_SEEDS}
    if args.split != "both":
        splits = {args.split: splits[args.split]} if args.split != "none" else {}
    report: dict[str, object] = {
        "frames_per_sequence": args.frames, "fps": FPS, "size": [WIDTH, HEIGHT],
        "options": {f: getattr(OPTIONS, f) for f in ("density", "empty_fraction",
                                                      "episode_s")},
        "detector": {"p_drop": P_DROP, "p_drop_occluded": P_DROP_OCCLUDED, "p_low": P_LOW,
                     "p_wrong_label": P_WRONG_LABEL, "jitter": JITTER,
                     "false_per_pair": FALSE_PER_PAIR},
        "tracker_config": repr(TrackerConfig()), "relink_config": repr(RelinkConfig()),
        "splits": {}}
    tables: list[h.Result] = []
    for split, seeds in splits.items():
        seqs = [make_sequence(s, args.frames) for s in seeds]
        res = evaluate(seqs, trackers)
        report["splits"][split] = {"seeds": list(seeds), "results": res}  # type: ignore[index]
        tables.append(result(f"{split} seeds {list(seeds)}, {args.frames} pairs each", res))
        if args.max_n:
            mx = synth_max_n(seqs)
            report["splits"][split]["max_n"] = mx  # type: ignore[index]
            tables.append(max_n_result(f"MaxN, {split} seeds", mx))
    if args.scorer_check:
        check = scorer_check(score)
        report["scorer_check"] = check
        tables.append(h.Result("tracking", "Scorer check (TUD, a published tracker's output)",
                               notes=[f"{seq}: {m}" for seq, m in check.items()]
                               or ["realdata 08b not found"]))
    if args.crocea:
        seqs_real = crocea_sequences(**({"seqs": args.crocea_seqs} if args.crocea_seqs
                                        else {}))
        if not seqs_real:
            tables.append(h.Result("tracking", "Crocea", notes=["realdata 08 not found"]))
        else:
            real = evaluate_real(seqs_real, args.crocea_fps, not args.no_bytetrack)
            report["crocea"] = real
            tables += real_results(f"crocea at {args.crocea_fps:g} fps", real)
    if args.live:
        live = live_results(args.live_seeds, args.live_frames, trackers)
        report["live"] = live
        tables.append(result(f"live runs, seeds {args.live_seeds}, {args.live_frames} pairs "
                             f"each, pairs seen {live['pairs_seen']}",
                             live["results"]))  # type: ignore[arg-type]
    if tables:
        tables[0].data = report
    else:
        tables = [h.Result("tracking", data=report)]
    h.write(args.out, "tracking", tables)
    print(h.markdown(tables))


if __name__ == "__main__":
    main()
