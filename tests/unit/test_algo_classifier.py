"""The stereo_ir classifier with real ONNX models: arrangements, softmax, threshold, bad input."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from trapflow_workers.scene_classifier import SceneClassifier

from tests.kits.onnx_models import colour_classifier, constant_detector
from trapflow.errors import WorkerError
from trapflow.testing.kit import make_context, make_pair

LABELS = "blue\ngreen\nred\n"


def _scene(bgr: tuple[int, int, int]) -> np.ndarray:
    img = np.zeros((480, 640, 3), np.uint8)
    img[:] = bgr
    img[100:200, 100:300] = (128, 128, 128)  # some clutter that does not change the answer
    return img


def _classifier(tmp_path: Path, arrangement: str, **params: Any) -> SceneClassifier:
    model = colour_classifier(tmp_path / f"{arrangement}.onnx", arrangement=arrangement)
    (tmp_path / "labels.txt").write_text(LABELS)
    clf = SceneClassifier()
    clf.configure(
        {"model": str(model), "labels": str(tmp_path / "labels.txt"), **params},
        make_context(pool="stereo"),
    )
    return clf


@pytest.mark.parametrize("arrangement", ["concat_channels", "side_by_side", "two_inputs"])
@pytest.mark.parametrize(
    ("bgr", "label"), [((200, 20, 20), "blue"), ((20, 200, 20), "green"), ((20, 20, 200), "red")]
)
def test_labels_match_the_scene(
    tmp_path: Path, arrangement: str, bgr: tuple[int, int, int], label: str
) -> None:
    clf = _classifier(tmp_path, arrangement)
    assert clf.arrangement == arrangement
    res = clf.process(make_pair(_scene(bgr), _scene(bgr)))
    assert res.label == label
    assert 0.5 < res.confidence <= 1.0


def test_below_threshold_is_none(tmp_path: Path) -> None:
    grey = _scene((100, 100, 100))  # equal logits: a third each after softmax
    res = _classifier(tmp_path, "concat_channels").process(make_pair(grey))
    assert res.label == "none" and res.confidence == pytest.approx(1 / 3, abs=1e-3)
    res = _classifier(tmp_path, "concat_channels", threshold=0.3).process(make_pair(grey))
    assert res.label == "blue" and res.confidence == pytest.approx(1 / 3, abs=1e-3)


@pytest.mark.parametrize(
    ("params", "error"),
    [
        ({"model": "{tmp}/missing.onnx"}, "model file not found"),
        ({"model": "{tmp}/m.onnx", "threshold": 2}, r"pools\.stereo\.params\.threshold"),
        ({"model": "{tmp}/m.onnx", "arrangement": "two_inputs"}, "expects 2 input"),
        ({"model": "{tmp}/m.onnx", "labels": "{tmp}/two.txt"}, "2 labels"),
        ({"model": "{tmp}/m.onnx", "labels": "{tmp}/nope.txt"}, "cannot read labels"),
        ({"model": "{tmp}/det.onnx"}, r"expected \[1, classes\], got \[1, 6, 10\]"),
    ],
)
def test_configure_rejects(tmp_path: Path, params: dict[str, Any], error: str) -> None:
    colour_classifier(tmp_path / "m.onnx")
    constant_detector(tmp_path / "det.onnx", np.zeros((1, 6, 10), np.float32), (32, 32))
    (tmp_path / "two.txt").write_text("a\nb\n")
    params = {k: v.format(tmp=tmp_path) if isinstance(v, str) else v for k, v in params.items()}
    with pytest.raises(WorkerError, match=error):
        SceneClassifier().configure(params, make_context(pool="stereo"))


def test_jpeg_pair_decoded_to_cover_the_input_classifies_alike(tmp_path: Path) -> None:
    """The classifier resizes each image to its input (128x64 here): a 1280x720 JPEG pair
    is decoded at 1/8 (160x90), and the scene comes out the same as from the full decode."""
    from tests import builders
    from trapflow.pools.pair_path import decode_image, decode_pair

    clf = _classifier(tmp_path, "concat_channels")
    assert clf.max_size == (128, 64)
    img = np.zeros((720, 1280, 3), np.uint8)
    img[:] = (20, 200, 20)
    img[100:400, 100:600] = (128, 128, 128)
    data = builders.jpeg(img)
    header = builders.pair_header(0, 1280, 720, "jpeg")
    pair = decode_pair(clf, header, data, data)
    assert pair.reduction == 8 and pair.left.shape == (90, 160, 3)
    small, whole = clf.process(pair), clf.process(make_pair(decode_image(data, header, "left")))
    assert small.label == whole.label == "green"
    assert small.confidence == pytest.approx(whole.confidence, abs=0.01)
