"""Helpers shared by the shipped algorithm plugins: model paths, labels, float tuples. The typed
params (Params, parse_params) and the frame check (check_frame) are the plugins' public API,
in trapflow.plugin."""

from __future__ import annotations

import ast
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from trapflow.plugin import WorkerError

PACKAGE_DIR = Path(__file__).resolve().parent
MODELS_DIR = PACKAGE_DIR / "models"

def model_path(value: str, default_name: str) -> Path:
    """The model file a plugin loads: `value` as given, or the packaged default when empty."""
    return Path(value).expanduser() if value else MODELS_DIR / default_name


def _labels_from_text(path: Path) -> list[str]:
    text = path.read_text(encoding="utf-8")
    if path.suffix.lower() == ".json":
        data = json.loads(text)
        return labels_from_names(data, str(path))
    return [line.strip() for line in text.splitlines() if line.strip() and not line.startswith("#")]


def labels_from_names(data: Any, origin: str) -> list[str]:
    """Labels from a list, or a {index: name} dict (Ultralytics `names` metadata)."""
    if isinstance(data, str):
        try:
            data = ast.literal_eval(data)  # literal_eval: metadata is data, never code
        except (ValueError, SyntaxError):
            raise WorkerError(
                f"{origin}: expected a list or dict of names, got {data[:60]!r}"
            ) from None
    if isinstance(data, dict):
        try:
            items = sorted((int(k), str(v)) for k, v in data.items())
        except (TypeError, ValueError):
            raise WorkerError(
                f"{origin}: expected integer class indices, got {list(data)[:5]}"
            ) from None
        if [i for i, _ in items] != list(range(len(items))):
            raise WorkerError(f"{origin}: expected class indices 0..{len(items) - 1}")
        return [name for _, name in items]
    if isinstance(data, (list, tuple)):
        return [str(v) for v in data]
    raise WorkerError(f"{origin}: expected a list or dict of names, got {type(data).__name__}")


def load_labels(
    explicit: str, model: Path, metadata: Mapping[str, str], key: str = "names"
) -> list[str] | None:
    """Class names: an explicit file, else the model's metadata, else a file beside the model.

    Files hold one label per line (blank lines and `#` comments skipped), or a JSON
    list / {index: name} object when the name ends in .json. None when nothing is found.
    """
    if explicit:
        path = Path(explicit).expanduser()
        try:
            return _labels_from_text(path)
        except OSError as exc:
            raise WorkerError(f"cannot read labels file {path}: {exc.strerror}") from None
        except json.JSONDecodeError as exc:
            raise WorkerError(f"labels file {path}: not valid JSON: {exc}") from None
    if key in metadata:
        return labels_from_names(metadata[key], f"model {model.name} metadata {key!r}")
    for name in (
        f"{model.stem}.labels",  # what the packaged demo models ship
        f"{model.stem}.labels.txt",
        f"{model.stem}_labels.txt",
        f"{model.stem}.names",
        f"{model.stem}.labels.json",
        "labels.txt",
    ):
        candidate = model.with_name(name)
        if candidate.is_file():
            return _labels_from_text(candidate)
    return None


def to_grey(img: np.ndarray) -> np.ndarray:
    """A grey image from a BGR one, or the image itself when it is grey already."""
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def floats(values: Sequence[float] | np.ndarray) -> tuple[float, ...]:
    """Plain Python floats (for msgspec result Structs) from any numeric sequence."""
    return tuple(float(v) for v in np.asarray(values, dtype=np.float64).ravel())

