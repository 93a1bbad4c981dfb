"""stereo_ir: an ONNX classifier on the stereo pair; top-1 label and confidence, `none` below a
threshold. Run it in a `latest` pool with a higher nice value so a slow model only drops pairs.

Input arrangements (params `arrangement`, else model metadata `arrangement`, else guessed):
  concat_channels  one input [1, 6, H, W]: left RGB then right RGB
  side_by_side     one input [1, 3, H, 2W]: left | right
  two_inputs       two inputs [1, 3, H, W]: left, right (in the model's input order)
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Annotated, Any, Literal

import cv2
import msgspec
import numpy as np

from trapflow.plugin import Context, Pair, StereoIR, Worker, WorkerError, check_frame, parse_params

from .common import load_labels, model_path
from .onnx_session import ModelParams, Session, open_session

log = logging.getLogger(__name__)

Arrangement = Literal["concat_channels", "side_by_side", "two_inputs"]
Side = Annotated[int, msgspec.Meta(ge=8, le=4096)]


class ClassifierParams(ModelParams):
    """`pools.stereo.params`: every key is optional (empty model: the packaged one)."""

    arrangement: Literal["auto", "concat_channels", "side_by_side", "two_inputs"] = "auto"
    """How the pair is fed to the model."""
    input_size: tuple[Side, Side] | None = None
    """(height, width) of one image for models with a dynamic input."""
    threshold: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)] = 0.5
    """Top-1 probability below this gives the label `none`."""
    softmax: Literal["auto", "always", "never"] = "auto"
    """auto: softmax unless the outputs already are probabilities (in 0..1, summing to 1)."""
    color: Literal["auto", "rgb", "bgr"] = "auto"
    """Channel order; auto = metadata `color_order`, else rgb."""
    scale: float | None = None
    """Pixel multiplier; default metadata `scale`, else 1/255."""
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)


def _arrangement(configured: str, meta: Mapping[str, str], inputs: Sequence[Any],
                 model: str) -> str:
    """How the model takes a pair: as configured, else as its metadata says, else guessed
    from its inputs (two inputs, six channels, or one image of both side by side)."""
    arrangement = configured if configured != "auto" else meta.get("arrangement", "auto")
    if arrangement == "auto":
        if len(inputs) == 2:
            arrangement = "two_inputs"
        elif len(inputs[0].shape) == 4 and inputs[0].shape[1] == 6:
            arrangement = "concat_channels"
        else:
            arrangement = "side_by_side"
    if arrangement not in ("concat_channels", "side_by_side", "two_inputs"):
        raise WorkerError(
            f"model {model}: metadata arrangement {arrangement!r} is not "
            "concat_channels, side_by_side or two_inputs"
        )
    return arrangement


class SceneClassifier(Worker):
    """Resize both images, arrange them as the model expects, classify the pair."""

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        p = parse_params(params, ClassifierParams, ctx.pool)
        self.p = p
        path = model_path(p.model, "scene_classifier.onnx")
        self.session: Session = open_session(path, p.providers, p.threads, settings=p)
        meta = self.session.metadata
        inputs = self.session.inputs
        arrangement = _arrangement(p.arrangement, meta, inputs, path.name)
        self.arrangement: str = arrangement
        want = {"concat_channels": (1, 6), "side_by_side": (1, 3), "two_inputs": (2, 3)}[
            arrangement
        ]
        shapes = [list(i.shape) for i in inputs]
        if len(inputs) != want[0] or any(len(s) != 4 or s[1] != want[1] for s in shapes):
            raise WorkerError(
                f"model {path.name}: arrangement {arrangement} expects {want[0]} "
                f"input(s) of [1, {want[1]}, H, W], got {shapes}"
            )
        h, w = shapes[0][2], shapes[0][3]
        if isinstance(h, int) and isinstance(w, int) and h > 0 and w > 0:
            size = (h, w // 2 if arrangement == "side_by_side" else w)
        elif p.input_size:
            size = p.input_size
        else:
            raise WorkerError(
                f"model {path.name} has a dynamic input: set "
                f"pools.{ctx.pool}.params.input_size to (height, width)"
            )
        self.size: tuple[int, int] = (int(size[0]), int(size[1]))
        # Each image is resized to exactly this: a JPEG is decoded at the DCT scale that
        # still covers it (1280x720 for 160x96: 1/4).
        self.max_size = (self.size[1], self.size[0])
        self.names = [i.name for i in inputs]
        self.dtype = self.session.input_dtype()
        color = p.color if p.color != "auto" else meta.get("color_order", "rgb").lower()
        self.rgb = color != "bgr"
        self.scale = p.scale if p.scale is not None else float(meta.get("scale", 1.0 / 255.0))
        self.mean = np.asarray(p.mean, np.float32).reshape(3, 1, 1)
        self.std = np.asarray(p.std, np.float32).reshape(3, 1, 1)
        self.labels = load_labels(p.labels, path, meta)
        probe = self._run(np.zeros((*self.size, 3), np.uint8), np.zeros((*self.size, 3), np.uint8))
        if self.labels is not None and len(self.labels) != probe.size:
            raise WorkerError(
                f"model {path.name} gives {probe.size} scores, "
                f"but {len(self.labels)} labels are given"
            )
        log.info(
            "classifier %s: %s, %dx%d per image, %d classes",
            path.name,
            arrangement,
            self.size[1],
            self.size[0],
            probe.size,
        )

    def _chw(self, img: np.ndarray) -> np.ndarray:
        img = cv2.resize(img, (self.size[1], self.size[0]), interpolation=cv2.INTER_AREA)
        if self.rgb:
            img = img[:, :, ::-1]
        x = img.transpose(2, 0, 1).astype(np.float32) * np.float32(self.scale)
        return np.asarray((x - self.mean) / self.std)

    def _run(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        a, b = self._chw(left), self._chw(right)
        if self.arrangement == "concat_channels":
            feeds = {self.names[0]: np.concatenate([a, b])[None]}
        elif self.arrangement == "side_by_side":
            feeds = {self.names[0]: np.concatenate([a, b], axis=2)[None]}
        else:
            feeds = {self.names[0]: a[None], self.names[1]: b[None]}
        feeds = {k: np.ascontiguousarray(v, dtype=self.dtype) for k, v in feeds.items()}
        out = self.session.run(feeds)[0]
        if out.shape[0] != 1 or out.size != out.shape[1 if out.ndim > 1 else 0]:
            raise WorkerError(f"classifier output: expected [1, classes], got {list(out.shape)}")
        return out.astype(np.float64).ravel()

    def process(self, pair: Pair) -> StereoIR:
        check_frame(pair)
        scores = self._run(pair.left, pair.right)
        is_prob = scores.min() >= 0 and scores.max() <= 1 and abs(scores.sum() - 1) < 1e-3
        if self.p.softmax == "always" or (self.p.softmax == "auto" and not is_prob):
            e = np.exp(scores - scores.max())
            scores = e / e.sum()
        top = int(scores.argmax())
        conf = float(scores[top])
        if conf < self.p.threshold:
            return StereoIR(label="none", confidence=conf, model=self.session.model_hash)
        label = self.labels[top] if self.labels else f"class{top}"
        return StereoIR(label=label, confidence=conf, model=self.session.model_hash)
