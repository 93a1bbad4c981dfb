"""Shared by the demo-model trainer and tests: synthetic samples, letterbox, decode, mAP.

Needs numpy and OpenCV only (no torch), so the accuracy test can use it.
"""

from __future__ import annotations

import cv2
import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.synth.dataset import labelled
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.tracking.assign import iou_matrix as iou

DET_SIZE = 320  # detector input, square, letterboxed
DET_CLASSES = ("crab", "scallop")
CLS_SIZE = (160, 96)  # classifier input per view (width, height)
CLS_LABELS = ("empty", "crab", "scallop")
PAD = 114


def letterbox(img: np.ndarray, size: int = DET_SIZE) -> tuple[np.ndarray, float, int, int]:
    """Ultralytics-style letterbox: scale to fit, pad with grey 114; returns img, scale, dx, dy."""
    h, w = img.shape[:2]
    s = min(size / w, size / h)
    nw, nh = int(round(w * s)), int(round(h * s))
    dx, dy = (size - nw) // 2, (size - nh) // 2
    out = np.full((size, size, 3), PAD, np.uint8)
    out[dy:dy + nh, dx:dx + nw] = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
    return out, s, dx, dy


def det_input(img: np.ndarray) -> tuple[np.ndarray, float, int, int]:
    """BGR image -> float32 [1, 3, S, S] RGB in 0..1, with the letterbox parameters."""
    lb, s, dx, dy = letterbox(img)
    x = lb[..., ::-1].transpose(2, 0, 1)[None].astype(np.float32) / 255.0
    return np.ascontiguousarray(x), s, dx, dy


def cls_input(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Pair -> float32 [1, 6, 96, 160]: left RGB then right RGB, each resized, in 0..1."""
    views = [cv2.resize(v, CLS_SIZE, interpolation=cv2.INTER_AREA)[..., ::-1]
             for v in (left, right)]
    x = np.concatenate(views, axis=2).transpose(2, 0, 1)[None].astype(np.float32) / 255.0
    return np.ascontiguousarray(x)


def samples(seeds: list[int], per_seed: int, step_s: float = 1.3, width: int = 1280,
            height: int = 720):
    """Yield (left, right, truth) from worlds with these seeds, spread over time."""
    rig = StereoRig.from_fov(width, height, 70.0, 0.12)
    for seed in seeds:
        opts = SynthOptions(density=1.5, empty_fraction=0.25, episode_s=12.0)
        world = World(rig, seed=seed, moving=seed % 4 == 3, rate_hz=15.0, options=opts)
        for k in range(per_seed):
            yield world.render(int(k * step_s * 15))


def det_targets(truth, s: float, dx: int, dy: int) -> list[tuple[int, float, float, float, float]]:
    """(class, x1, y1, x2, y2) in detector input pixels for the labelled animals."""
    out = []
    for o in labelled(truth):
        if o.label in DET_CLASSES:
            x1, y1, x2, y2 = o.box
            out.append((DET_CLASSES.index(o.label), x1 * s + dx, y1 * s + dy, x2 * s + dx,
                        y2 * s + dy))
    return out


def decode(out: np.ndarray, conf: float = 0.05, iou_thr: float = 0.5
           ) -> list[tuple[int, float, np.ndarray]]:
    """YOLOv8 layout [1, 4+nc, N] -> (class, score, box x1y1x2y2) after per-class NMS."""
    p = out[0].T
    boxes_c, scores = p[:, :4], p[:, 4:]
    cls = scores.argmax(1)
    sc = scores.max(1)
    keep = sc > conf
    b = boxes_c[keep]
    xyxy = np.stack([b[:, 0] - b[:, 2] / 2, b[:, 1] - b[:, 3] / 2, b[:, 0] + b[:, 2] / 2,
                     b[:, 1] + b[:, 3] / 2], 1)
    cls, sc = cls[keep], sc[keep]
    result = []
    for c in np.unique(cls):
        idx = np.nonzero(cls == c)[0]
        idx = idx[np.argsort(-sc[idx])]
        while len(idx):
            i = idx[0]
            result.append((int(c), float(sc[i]), xyxy[i]))
            if len(idx) == 1:
                break
            rest = idx[1:]
            idx = rest[iou(xyxy[i:i + 1], xyxy[rest])[0] < iou_thr]
    return result


def average_precision(dets: list[tuple[int, float, np.ndarray]],
                      gts: list[list[np.ndarray]]) -> float:
    """VOC all-point AP@0.5 of one class. dets: (image, score, box); gts: boxes per image."""
    n_gt = sum(len(g) for g in gts)
    if n_gt == 0:
        return float("nan")
    used = [np.zeros(len(g), bool) for g in gts]
    tp = []
    for img, _, box in sorted(dets, key=lambda d: -d[1]):
        g = gts[img]
        ok = False
        if len(g):
            ious = iou(box[None], np.array(g))[0]
            j = int(ious.argmax())
            if ious[j] >= 0.5 and not used[img][j]:
                used[img][j] = True
                ok = True
        tp.append(ok)
    tps = np.cumsum(tp)
    fps = np.cumsum([not t for t in tp])
    recall = tps / n_gt
    precision = tps / np.maximum(tps + fps, 1)
    mrec = np.concatenate([[0.0], recall, [1.0]])
    mpre = np.concatenate([[0.0], precision, [0.0]])
    for i in range(len(mpre) - 2, -1, -1):
        mpre[i] = max(mpre[i], mpre[i + 1])
    idx = np.nonzero(mrec[1:] != mrec[:-1])[0]
    return float(np.sum((mrec[idx + 1] - mrec[idx]) * mpre[idx + 1]))
