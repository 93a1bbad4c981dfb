"""Tiny ONNX detectors with the exact output layouts of YOLOX and YOLOv5, built with onnx.helper.

No trained weights: each head level average-pools the image by its stride and maps the
pooled colour through a seeded random 1x1 convolution, so every box, objectness and class
score depends on the pixels under its grid cell. Where the letterbox puts the image
therefore changes what is detected, and where.

YOLOX (yolox/models/yolo_head.py): per stride [reg(4), obj, cls] with sigmoid on obj and
cls, flattened and concatenated to [1, N, 5+nc], N = sum((H/s) * (W/s)); with
decode_in_inference the graph adds (xy + grid) * s and exp(wh) * s.
YOLOv5 (models/yolo.py Detect): per stride 3 anchors x [xywh, obj, cls], all sigmoided,
xy = (2 sig - 0.5 + grid) * s, wh = (2 sig)^2 * anchor, to [1, 3 * N, 5+nc].
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
GAIN = 4.0  # logit change across the colour range: colours decide objectness and class
STRIDES = (8, 16, 32)
# YOLOv5s anchors (pixels) per stride, models/yolov5s.yaml
V5_ANCHORS = {
    8: [(10, 13), (16, 30), (33, 23)],
    16: [(30, 61), (62, 45), (59, 119)],
    32: [(116, 90), (156, 198), (373, 326)],
}


class _Graph:
    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []

    def const(self, name: str, value: np.ndarray) -> str:
        self.inits.append(numpy_helper.from_array(np.asarray(value), name))
        return name

    def op(self, kind: str, inputs: list[str], output: str, **attrs: object) -> str:
        self.nodes.append(helper.make_node(kind, inputs, [output], **attrs))
        return output

    def pooled_conv(self, s: int, weight: np.ndarray, bias: np.ndarray, jitter: np.ndarray) -> str:
        """[1, C, H/s, W/s]: 1x1 convolution of the image average-pooled by s, plus a
        per-cell term `jitter` (C, H/s, W/s), as a trained network's context would add."""
        pool = self.op("AveragePool", ["images"], f"pool{s}", kernel_shape=[s, s], strides=[s, s])
        w = self.const(f"w{s}", weight.astype(np.float32)[:, :, None, None])
        b = self.const(f"b{s}", bias.astype(np.float32))
        conv = self.op("Conv", [pool, w, b], f"conv{s}")
        return self.op("Add", [conv, self.const(f"j{s}", jitter[None].astype(np.float32))], f"x{s}")

    def save(
        self,
        path: Path,
        input_hw: tuple[int, int],
        out: str,
        shape: list[int],
        metadata: dict[str, str],
    ) -> Path:
        image = helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, *input_hw])
        output = helper.make_tensor_value_info(out, TensorProto.FLOAT, shape)
        graph = helper.make_graph(self.nodes, "tiny_yolo", [image], [output], self.inits)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
        model.ir_version = 8
        for key, value in metadata.items():
            entry = model.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.checker.check_model(model)
        onnx.save(model, str(path))
        return path


def _weights(rng: np.random.Generator, n_out: int, pixel_range: float) -> np.ndarray:
    """Random 1x1 weights for inputs in 0..pixel_range, giving logits of order `gain`."""
    return rng.normal(0.0, GAIN / pixel_range, (n_out, 3))


def _jitter(
    rng: np.random.Generator, channels: int, obj: list[int], hw: tuple[int, int]
) -> np.ndarray:
    """Small per-cell objectness logits: cells of one uniform colour (clipped highlights,
    dark cloth) would otherwise score exactly alike, and which of several equal boxes NMS
    keeps depends on the sort algorithm, in any toolchain."""
    out = np.zeros((channels, *hw))
    out[obj] = rng.normal(0.0, 0.05, (len(obj), *hw))
    return out


def _grey_bias(weight: np.ndarray, pixel_range: float) -> np.ndarray:
    """The bias that makes every output zero on the 114-grey padding: the padding is
    never an object, and objects come only from the photo's colours."""
    return -weight @ np.full(3, 114.0 / 255.0 * pixel_range)


def yolox_model(
    path: Path,
    input_hw: tuple[int, int],
    nc: int,
    decoded: bool,
    seed: int = 0,
    obj_bias: float = -3.0,
) -> Path:
    """A YOLOX-layout detector for BGR input in 0..255 (YOLOX's preproc, no scaling)."""
    rng = np.random.default_rng(seed)
    g = _Graph()
    h, w = input_hw
    c = 5 + nc
    # obj and cls go through a sigmoid, reg does not: out = m * sigmoid(x) + (1 - m) * x
    mask = np.zeros((1, c, 1, 1), np.float32)
    mask[:, 4:] = 1.0
    g.const("sig_mask", mask)
    g.const("keep_mask", 1.0 - mask)
    levels = []
    for s in STRIDES:
        weight = _weights(rng, c, 255.0)
        weight[:4] /= GAIN  # box offsets and log sizes of order one
        bias = _grey_bias(weight, 255.0)
        bias[0:2] += 0.5  # centre offsets near the middle of the cell
        bias[2:4] += np.log(3.0)  # boxes about three strides wide
        bias[4] += obj_bias
        bias[5:] += rng.normal(0.0, 0.3, nc)
        x = g.pooled_conv(s, weight, bias, _jitter(rng, c, [4], (h // s, w // s)))
        sig = g.op("Sigmoid", [x], f"sig{s}")
        a = g.op("Mul", [sig, "sig_mask"], f"a{s}")
        b = g.op("Mul", [x, "keep_mask"], f"k{s}")
        head = g.op("Add", [a, b], f"head{s}")
        shape = g.const(f"shape{s}", np.array([1, c, (h // s) * (w // s)], np.int64))
        levels.append(g.op("Reshape", [head, shape], f"flat{s}"))
    cat = g.op("Concat", levels, "cat", axis=2)
    out = g.op("Transpose", [cat], "raw" if decoded else "output", perm=[0, 2, 1])
    n = sum((h // s) * (w // s) for s in STRIDES)
    if decoded:
        grid, stride = [], []
        for s in STRIDES:
            gy, gx = np.meshgrid(np.arange(h // s), np.arange(w // s), indexing="ij")
            grid.append(np.stack([gx.ravel(), gy.ravel()], 1))
            stride.append(np.full((gx.size, 1), s))
        add = np.zeros((1, n, c), np.float32)
        add[0, :, :2] = np.concatenate(grid)
        mul = np.ones((1, n, c), np.float32)
        mul[0, :, :4] = np.concatenate(stride)
        exp_mask = np.zeros((1, 1, c), np.float32)
        exp_mask[..., 2:4] = 1.0
        g.const("exp_mask", exp_mask)
        g.const("lin_mask", 1.0 - exp_mask)
        e = g.op("Exp", [out], "exp")
        e = g.op("Mul", [e, "exp_mask"], "exp_part")
        lin = g.op("Mul", [out, "lin_mask"], "lin_part")
        both = g.op("Add", [e, lin], "both")
        shifted = g.op("Add", [both, g.const("grid", add)], "shifted")
        out = g.op("Mul", [shifted, g.const("strides", mul)], "output")
    return g.save(path, input_hw, out, [1, n, c], {})


def yolov5_model(
    path: Path,
    input_hw: tuple[int, int],
    nc: int,
    names: list[str],
    seed: int = 0,
    obj_bias: float = -7.0,
) -> Path:
    """A YOLOv5-layout detector for RGB input in 0..1 (YOLOv5's letterbox, /255)."""
    rng = np.random.default_rng(seed)
    g = _Graph()
    h, w = input_hw
    c = 5 + nc
    levels = []
    for s in STRIDES:
        ny, nx = h // s, w // s
        weight = _weights(rng, 3 * c, 1.0)
        weight.reshape(3, c, 3)[:, :4] /= GAIN
        bias = _grey_bias(weight, 1.0).reshape(3, c)
        bias[:, 4] += obj_bias
        bias[:, 5:] += rng.normal(0.0, 0.3, (3, nc))
        jitter = _jitter(rng, 3 * c, [4, c + 4, 2 * c + 4], (ny, nx))
        x = g.pooled_conv(s, weight, bias.ravel(), jitter)
        x = g.op("Reshape", [x, g.const(f"s5_{s}", np.array([1, 3, c, ny, nx], np.int64))], f"r{s}")
        x = g.op("Transpose", [x], f"t{s}", perm=[0, 1, 3, 4, 2])  # [1, 3, ny, nx, c]
        y = g.op("Sigmoid", [x], f"y{s}")
        # xy = 2 s y + (grid - 0.5) s ; wh = 4 anchor y^2 ; the rest = y
        lin = np.ones((1, 1, 1, 1, c), np.float32)
        lin[..., :2] = 2.0 * s
        lin[..., 2:4] = 0.0
        quad = np.zeros((1, 3, 1, 1, c), np.float32)
        quad[0, :, 0, 0, 2:4] = 4.0 * np.asarray(V5_ANCHORS[s], np.float32)
        gy, gx = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
        off = np.zeros((1, 1, ny, nx, c), np.float32)
        off[0, 0, :, :, 0] = (gx - 0.5) * s
        off[0, 0, :, :, 1] = (gy - 0.5) * s
        a = g.op("Mul", [y, g.const(f"lin{s}", lin)], f"ly{s}")
        y2 = g.op("Mul", [y, y], f"yy{s}")
        b = g.op("Mul", [y2, g.const(f"quad{s}", quad)], f"qy{s}")
        ab = g.op("Add", [a, b], f"ab{s}")
        dec = g.op("Add", [ab, g.const(f"off{s}", off)], f"dec{s}")
        shape = g.const(f"flat_shape{s}", np.array([1, 3 * ny * nx, c], np.int64))
        levels.append(g.op("Reshape", [dec, shape], f"flat{s}"))
    out = g.op("Concat", levels, "output0", axis=1)
    n = 3 * sum((h // s) * (w // s) for s in STRIDES)
    meta = {"stride": "32", "names": str(dict(enumerate(names)))}
    return g.save(path, input_hw, out, [1, n, c], meta)
