"""Helpers shared by the algorithm plugins: typed params, model paths, labels, frame checks.

Every plugin validates its pool's `params:` with a msgspec Struct through parse_params(),
so errors name `pools.<pool>.params.<key>` and say what was expected.
"""

from __future__ import annotations

import ast
import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import cv2
import msgspec
import numpy as np

from trapflow.plugin import Pair, WorkerError, reduced_size

PACKAGE_DIR = Path(__file__).resolve().parent
MODELS_DIR = PACKAGE_DIR / "models"

S = TypeVar("S", bound=msgspec.Struct)


class Params(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Base of every plugin's params Struct: keyword-only, unknown keys rejected."""


_AT = re.compile(r" - at `\$(?P<path>[^`]*)`")
_UNKNOWN = re.compile(r"unknown field `(?P<key>[^`]+)`")


def parse_params(params: Mapping[str, Any], cls: type[S], pool: str) -> S:
    """Validate a pool's params into `cls`; WorkerError names `pools.<pool>.params.<key>`."""
    prefix = f"pools.{pool}.params"
    if not isinstance(params, Mapping):
        raise WorkerError(f"{prefix}: expected a mapping, got {type(params).__name__}")
    try:
        return msgspec.convert(dict(params), cls, strict=True)
    except msgspec.ValidationError as exc:
        text = str(exc)
        at = _AT.search(text)
        path = at.group("path") if at else ""
        unknown = _UNKNOWN.search(text)
        if unknown:
            path += f".{unknown.group('key')}"
            fields = ", ".join(cls.__struct_fields__)
            text = f"unknown key (expected one of: {fields})"
        reason = _AT.sub("", text)
        raise WorkerError(f"{prefix}{path}: {reason}") from None


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


def check_frame(pair: Pair, size: tuple[int, int] | None = None, what: str = "",
                grey_ok: bool = False) -> None:
    """Raise WorkerError unless both images are HxWx3 uint8 (or HxW with grey_ok) of the
    header's (and `size`'s) size, reduced by pair.reduction (a JPEG decoded at a reduced
    DCT scale for the plugin's max_size)."""
    w, h = pair.header.width, pair.header.height
    iw, ih = reduced_size((w, h), pair.reduction)
    for side, img in (("left", pair.left), ("right", pair.right)):
        if (
            not isinstance(img, np.ndarray)
            or img.dtype != np.uint8
            or not ((img.ndim == 3 and img.shape[2] == 3) or (grey_ok and img.ndim == 2))
        ):
            shape = getattr(img, "shape", None)
            raise WorkerError(
                f"pair {pair.header.seq}: expected a BGR uint8 {side} image, "
                f"got shape {shape} dtype {getattr(img, 'dtype', None)}"
            )
        if img.shape[:2] != (ih, iw):
            at = f" at 1/{pair.reduction}: {iw}x{ih}" if pair.reduction > 1 else ""
            raise WorkerError(
                f"pair {pair.header.seq}: {side} image is "
                f"{img.shape[1]}x{img.shape[0]}, header says {w}x{h}{at}"
            )
    if size is not None and size != (w, h):
        raise WorkerError(
            f"pair {pair.header.seq}: frame is {w}x{h}, expected {size[0]}x{size[1]}"
            f"{' (' + what + ')' if what else ''}"
        )


def floats(values: Sequence[float] | np.ndarray) -> tuple[float, ...]:
    """Plain Python floats (for msgspec result Structs) from any numeric sequence."""
    return tuple(float(v) for v in np.asarray(values, dtype=np.float64).ravel())
