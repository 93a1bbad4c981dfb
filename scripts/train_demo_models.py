"""Train the demo crab detector on the synthetic world and export ONNX (dev only: needs torch).

    python scripts/train_demo_models.py [--out workers/models] [--seeds 40] [--epochs 12]
    python scripts/train_demo_models.py --set-metadata   # only (re)write the ONNX metadata

Detector: Ultralytics YOLOv8 output layout [1, 4+nc, N] (cx, cy, w, h in input pixels,
then per-class scores, no objectness) on a 320x320 letterboxed RGB input in 0..1, with the
metadata CrabDetector reads (names, imgsz, color_order, scale, layout).
The stereo scene classifier is trained by scripts/train_scene_classifier.py.
Training seeds 1000+, evaluation seeds 9000+ (never used for training).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
import synth_demo_data as sd

STRIDE = 8
GRID = sd.DET_SIZE // STRIDE
DET_METADATA = {
    "names": str(dict(enumerate(sd.DET_CLASSES))),
    "imgsz": json.dumps([sd.DET_SIZE, sd.DET_SIZE]),
    "color_order": "rgb",
    "scale": repr(1.0 / 255.0),
    "layout": "yolov8",
    "task": "detect",
    "description": "trapflow demo crab and scallop detector (synthetic data only)",
}


def set_metadata(path: Path, meta: dict[str, str]) -> None:
    """Replace the ONNX custom metadata (what the runtime plugins read) in place."""
    import onnx

    proto = onnx.load(str(path))
    del proto.metadata_props[:]
    for k, v in meta.items():
        proto.metadata_props.add(key=k, value=v)
    onnx.save(proto, str(path))


def block(cin: int, cout: int, stride: int = 1, dil: int = 1) -> nn.Module:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, padding=dil, dilation=dil, bias=False),
                         nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class Detector(nn.Module):
    """Tiny anchor-free detector, one stride-8 head, fed by a stride-16 context branch."""

    def __init__(self, nc: int) -> None:
        super().__init__()
        self.nc = nc
        self.stem = nn.Sequential(block(3, 16, 2), block(16, 32, 2), block(32, 32),
                                  block(32, 64, 2), block(64, 64))
        self.ctx = nn.Sequential(block(64, 96, 2), block(96, 96), block(96, 96, dil=2))
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.fuse = nn.Sequential(block(160, 64), block(64, 64))
        self.head = nn.Conv2d(64, 4 + nc, 1)
        ys, xs = torch.meshgrid(torch.arange(GRID), torch.arange(GRID), indexing="ij")
        self.register_buffer("gx", xs.reshape(1, -1).float())
        self.register_buffer("gy", ys.reshape(1, -1).float())
        nn.init.constant_(self.head.bias[4:], -4.0)

    def raw(self, x: torch.Tensor) -> torch.Tensor:
        f = self.stem(x)
        f = self.fuse(torch.cat([f, self.up(self.ctx(f))], 1))
        return self.head(f).flatten(2)  # [B, 4+nc, N]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r = self.raw(x)
        cx = (self.gx + 0.5 + (torch.sigmoid(r[:, 0]) * 4 - 2)) * STRIDE
        cy = (self.gy + 0.5 + (torch.sigmoid(r[:, 1]) * 4 - 2)) * STRIDE
        w = torch.exp(r[:, 2].clamp(-4, 4)) * 32.0
        h = torch.exp(r[:, 3].clamp(-4, 4)) * 32.0
        return torch.cat([torch.stack([cx, cy, w, h], 1), torch.sigmoid(r[:, 4:])], 1)


def gather(seeds: list[int], per_seed: int):
    det_x, det_t = [], []
    for left, _right, truth in sd.samples(seeds, per_seed):
        x, s, dx, dy = sd.det_input(left)
        det_x.append(np.round(x[0] * 255).astype(np.uint8))
        det_t.append(sd.det_targets(truth, s, dx, dy))
    return np.stack(det_x), det_t


def encode_targets(targets, nc: int):
    """Centre sampling: cells within 1.5 cells of a box centre (and inside it) are positive."""
    cls_t = np.zeros((len(targets), nc, GRID * GRID), np.float32)
    box_t = np.zeros((len(targets), 4, GRID * GRID), np.float32)
    pos = np.zeros((len(targets), GRID * GRID), bool)
    for b, tl in enumerate(targets):
        for c, x1, y1, x2, y2 in sorted(tl, key=lambda t: -(t[3] - t[1]) * (t[4] - t[2])):
            cx, cy, w, h = (x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1
            gx, gy = cx / STRIDE - 0.5, cy / STRIDE - 0.5
            r = 1.5 if min(w, h) > 12 else 1.0
            for j in range(int(np.floor(gy - r)), int(np.ceil(gy + r)) + 1):
                for i in range(int(np.floor(gx - r)), int(np.ceil(gx + r)) + 1):
                    if not (0 <= i < GRID and 0 <= j < GRID) or abs(i - gx) > r or abs(j - gy) > r:
                        continue
                    k = j * GRID + i
                    cls_t[b, c, k] = 1.0
                    box_t[b, :, k] = (cx, cy, w, h)
                    pos[b, k] = True
    return cls_t, box_t, pos


def train_detector(data, epochs: int) -> Detector:
    x, targets = data
    nc = len(sd.DET_CLASSES)
    cls_t, box_t, pos = encode_targets(targets, nc)
    model = Detector(nc)
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3, weight_decay=1e-4)
    n = len(x)
    steps = epochs * ((n + 31) // 32)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, 3e-3, total_steps=steps)
    rng = np.random.default_rng(0)
    for ep in range(epochs):
        order = rng.permutation(n)
        tot = 0.0
        for i in range(0, n, 32):
            idx = order[i:i + 32]
            xb = torch.from_numpy(x[idx].astype(np.float32) / 255.0)
            flip = rng.random() < 0.5
            ct, bt, pt = (torch.from_numpy(cls_t[idx]), torch.from_numpy(box_t[idx]),
                          torch.from_numpy(pos[idx]))
            if flip:  # horizontal flip of image and targets
                xb = xb.flip(3)
                ct = ct.reshape(-1, nc, GRID, GRID).flip(3).reshape(-1, nc, GRID * GRID)
                bt = bt.reshape(-1, 4, GRID, GRID).flip(3).reshape(-1, 4, GRID * GRID).clone()
                bt[:, 0] = torch.where(bt[:, 2] > 0, sd.DET_SIZE - bt[:, 0], bt[:, 0])
                pt = pt.reshape(-1, GRID, GRID).flip(2).reshape(-1, GRID * GRID)
            out = model(xb)
            raw = model.raw(xb) if False else None  # noqa: F841
            scores = out[:, 4:].clamp(1e-6, 1 - 1e-6)
            bce = -(ct * torch.log(scores) + (1 - ct) * torch.log(1 - scores))
            focal = bce * ((ct - scores).abs() ** 2)
            l_cls = focal.sum() / max(float(pt.sum()), 1.0)
            m = pt.unsqueeze(1).float()
            l_xy = ((out[:, :2] - bt[:, :2]).abs() / STRIDE * m).sum()
            l_wh = ((torch.log(out[:, 2:4] + 1) - torch.log(bt[:, 2:4] + 1)).abs() * m).sum()
            loss = l_cls + (l_xy + 2.0 * l_wh) / max(float(pt.sum()), 1.0)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            tot += float(loss)
        print(f"detector epoch {ep + 1}/{epochs} loss {tot / ((n + 31) // 32):.4f}", flush=True)
    return model.eval()


def export(model: nn.Module, shape: tuple[int, ...], path: Path, names: list[str]) -> None:
    torch.onnx.export(model, torch.zeros(shape), str(path), input_names=["images"],
                      output_names=names, opset_version=17, dynamo=False)
    set_metadata(path, DET_METADATA)


def evaluate(out_dir: Path, seeds: list[int], per_seed: int) -> dict[str, float]:
    import onnxruntime as ort

    det = ort.InferenceSession(str(out_dir / "crab_detector.onnx"),
                               providers=["CPUExecutionProvider"])
    dets: dict[int, list] = {c: [] for c in range(len(sd.DET_CLASSES))}
    gts: dict[int, list] = {c: [] for c in range(len(sd.DET_CLASSES))}
    total = 0
    t_det = 0.0
    for img, (left, _right, truth) in enumerate(sd.samples(seeds, per_seed)):
        x, s, dx, dy = sd.det_input(left)
        t0 = time.perf_counter()
        out = det.run(None, {"images": x})[0]
        t_det += time.perf_counter() - t0
        for c in gts:
            gts[c].append([np.array(t[1:]) for t in sd.det_targets(truth, s, dx, dy) if t[0] == c])
        for c, score, box in sd.decode(out):
            dets[c].append((img, score, box))
        total += 1
    return {"images": total,
            "map50_crab": round(sd.average_precision(dets[0], gts[0]), 3),
            "map50_scallop": round(sd.average_precision(dets[1], gts[1]), 3),
            "detector_ms": round(1000 * t_det / total, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="workers/models")
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--per-seed", type=int, default=40)
    ap.add_argument("--epochs", type=int, default=12)
    ap.add_argument("--eval-only", action="store_true")
    ap.add_argument("--set-metadata", action="store_true")
    args = ap.parse_args()
    torch.manual_seed(0)
    torch.set_num_threads(2)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.set_metadata:
        set_metadata(out / "crab_detector.onnx", DET_METADATA)
        return
    if not args.eval_only:
        t0 = time.time()
        dx, dt = gather(list(range(1000, 1000 + args.seeds)), args.per_seed)
        print(f"data: {len(dx)} images in {time.time() - t0:.0f} s", flush=True)
        t0 = time.time()
        det = train_detector((dx, dt), args.epochs)
        export(det, (1, 3, sd.DET_SIZE, sd.DET_SIZE), out / "crab_detector.onnx", ["output0"])
        print(f"detector trained in {time.time() - t0:.0f} s", flush=True)
        (out / "crab_detector.labels").write_text("".join(c + "\n" for c in sd.DET_CLASSES))
    metrics = evaluate(out, list(range(9000, 9012)), 40)
    print(json.dumps(metrics), flush=True)


if __name__ == "__main__":
    main()
