"""Real tracking data for the tracking bench (benchmarks/tracking.py): real fish tracks
with detections made from them, and a check that the bench's scorer scores as published.

Crocea (realdata 08_fish_tracking_crocea): MOTChallenge ground truth of 12-25 large yellow
croakers per tank, 8 videos, no images and no detections. The detections are made from the
truth the way a detector fails, seeded per sequence (`crocea_detections`):

- a fish is missed with probability P_DROP, plus P_DROP_OCCLUDED times the share of its box
  that other fish cover (crossing fish are where a detector loses one);
- a found fish is sometimes placed where it was one frame before (P_LATE: a box from a
  frame in flight, or motion blur);
- its box centre and sides are jittered by JITTER box sides (normal, the sides
  log-normal);
- its confidence is low (0.15-0.5, ByteTrack's second stage) with probability P_LOW plus
  P_LOW_OCCLUDED times the covered share, else 0.5-0.95;
- FALSE_PER_PAIR false boxes a frame on average (Poisson), sized like the sequence's fish,
  anywhere in the frame the fish use, most of them weak;
- the recogniser sees one pair in N: rows are kept for frames 1, 1 + N, 1 + 2N, ...

The frame rate is not published with the data; the bench takes CROCEA_FPS (60, the rate of
such lab-tank recordings) unless told another (--crocea-fps).

TUD (realdata 08b_mot_scorer_check_tud): ground truth of two MOT15 sequences and a published
tracker's output on them, with its published IDF1, MOTA, FP, FN and ID switches;
`scorer_check` scores that output with the bench's own scorer.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from trapflow.tracking.motformat import MotRow, read_mot

REPO = Path(__file__).resolve().parent.parent
CROCEA_SEQS = (6, 7, 14, 15, 16, 18, 19, 20)
CROCEA_FPS = 60.0
CROCEA_SEED = 35  # the detections' seed, mixed with the sequence's number

P_DROP = 0.08
P_DROP_OCCLUDED = 0.5
P_LATE = 0.05
JITTER = 0.04
P_LOW = 0.15
P_LOW_OCCLUDED = 0.4
FALSE_PER_PAIR = 0.4

# MOTChallenge's published numbers for the CEM tracker (the devkit's readme).
TUD_PUBLISHED = {
    "TUD-Campus": {"IDF1": 55.8, "MOTA": 52.6, "FP": 13, "FN": 150, "IDSW": 7},
    "TUD-Stadtmitte": {"IDF1": 64.5, "MOTA": 56.4, "FP": 45, "FN": 452, "IDSW": 7},
}


def realdata_root() -> Path:
    """$TRAPFLOW_REALDATA, else the shared kit beside the repository."""
    env = os.environ.get("TRAPFLOW_REALDATA")
    return Path(env) if env else REPO.parent / "shared" / "realdata"


@dataclass(frozen=True)
class RealSequence:
    """Ground truth and detections (every frame) of one real sequence."""

    name: str
    gt: list[MotRow]
    dets: list[MotRow]


def covered_share(boxes: np.ndarray) -> np.ndarray:
    """For each box (x1 y1 x2 y2), the largest share of its area one other box covers."""
    n = len(boxes)
    if n < 2:
        return np.zeros(n)
    x1 = np.maximum(boxes[:, None, 0], boxes[None, :, 0])
    y1 = np.maximum(boxes[:, None, 1], boxes[None, :, 1])
    x2 = np.minimum(boxes[:, None, 2], boxes[None, :, 2])
    y2 = np.minimum(boxes[:, None, 3], boxes[None, :, 3])
    inter = np.clip(x2 - x1, 0, None) * np.clip(y2 - y1, 0, None)
    np.fill_diagonal(inter, 0.0)
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    out: np.ndarray = np.clip(inter.max(axis=1) / np.maximum(area, 1e-9), 0.0, 1.0)
    return out


def crocea_detections(gt: list[MotRow], seed: int) -> list[MotRow]:
    """Detector output for every frame of a ground truth (seeded), MOT rows with id -1 and
    the truth's class."""
    rng = np.random.default_rng([CROCEA_SEED, seed])
    by_frame: dict[int, list[MotRow]] = {}
    for r in gt:
        by_frame.setdefault(r.frame, []).append(r)
    prev: dict[int, MotRow] = {}
    sizes = np.array([[r.w, r.h] for r in gt])
    x_hi = max(r.x + r.w for r in gt)
    y_hi = max(r.y + r.h for r in gt)
    out = []
    for frame in range(1, max(by_frame) + 1):
        rows = by_frame.get(frame, [])
        boxes = np.array([[r.x, r.y, r.x + r.w, r.y + r.h] for r in rows]).reshape(-1, 4)
        cover = covered_share(boxes)
        for r, occ in zip(rows, cover.tolist(), strict=True):
            src = prev.get(r.id, r) if rng.random() < P_LATE else r
            if rng.random() < P_DROP + P_DROP_OCCLUDED * occ:
                continue
            w, h = src.w, src.h
            cx = src.x + w / 2 + rng.normal(0, JITTER) * w
            cy = src.y + h / 2 + rng.normal(0, JITTER) * h
            w *= float(np.exp(rng.normal(0, JITTER)))
            h *= float(np.exp(rng.normal(0, JITTER)))
            low = rng.random() < P_LOW + P_LOW_OCCLUDED * occ
            conf = rng.uniform(0.15, 0.5) if low else rng.uniform(0.5, 0.95)
            out.append(MotRow(frame=frame, id=-1, x=cx - w / 2, y=cy - h / 2, w=w, h=h,
                              conf=float(conf), cls=r.cls))
        for _ in range(rng.poisson(FALSE_PER_PAIR)):
            w, h = sizes[rng.integers(len(sizes))]
            x, y = rng.uniform(0, x_hi - w), rng.uniform(0, y_hi - h)
            conf = rng.uniform(0.1, 0.45) if rng.random() < 0.8 else rng.uniform(0.5, 0.7)
            out.append(MotRow(frame=frame, id=-1, x=float(x), y=float(y), w=float(w),
                              h=float(h), conf=float(conf), cls=gt[0].cls))
        prev.update({r.id: r for r in rows})
    return out


def crocea_sequences(root: Path | None = None, seqs: tuple[int, ...] = CROCEA_SEQS
                     ) -> list[RealSequence]:
    """The crocea sequences with their detections; [] when the kit is not there."""
    base = (root or realdata_root()) / "08_fish_tracking_crocea" / "gt"
    out = []
    for n in seqs:
        path = base / f"crocea{n}" / "gt" / "gt.txt"
        if not path.is_file():
            return []
        gt = read_mot(path)
        out.append(RealSequence(name=f"crocea{n}", gt=gt, dets=crocea_detections(gt, n)))
    return out


def scorer_check(score_fn: object, root: Path | None = None) -> dict[str, dict[str, float]]:
    """The bench's scorer on the published tracker's output of each TUD sequence, beside the
    published numbers; {} when the kit is not there."""
    base = (root or realdata_root()) / "08b_mot_scorer_check_tud"
    out: dict[str, dict[str, float]] = {}
    for seq, published in TUD_PUBLISHED.items():
        gt_path = base / "gt" / seq / "gt" / "gt.txt"
        hyp_path = base / "trackers" / "CEM" / f"{seq}.txt"
        if not (gt_path.is_file() and hyp_path.is_file()):
            return {}
        gt, hyp = _read_boxes(gt_path), _read_boxes(hyp_path)
        frames = sorted({r.frame for r in gt} | {r.frame for r in hyp})
        got = score_fn(gt, hyp, frames)  # type: ignore[operator]
        out[seq] = {"IDF1": round(100 * got["IDF1"], 1), "MOTA": round(100 * got["MOTA"], 1),
                    "FP": got["FP"], "FN": got["FN"], "IDSW": got["IDSW"],
                    "HOTA": round(100 * got["HOTA"], 1),
                    **{f"published_{k}": v for k, v in published.items()}}
    return out


def _read_boxes(path: Path) -> list[MotRow]:
    """frame,id,x,y,w,h of a MOT15 file (its later columns are world coordinates in some
    sequences, not a class)."""
    a = np.loadtxt(path, delimiter=",", ndmin=2)
    return [MotRow(frame=int(r[0]), id=int(r[1]), x=float(r[2]), y=float(r[3]),
                   w=float(r[4]), h=float(r[5])) for r in a]
