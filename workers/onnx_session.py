"""onnxruntime sessions for the ONNX plugins: providers in order of preference, with fallback.

One intra-op thread by default: a pool runs one session per worker process, and
several sessions spinning on all cores would fight each other.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import msgspec
import numpy as np
import onnxruntime as ort
from trapflow_workers.common import Params

from trapflow.errors import WorkerError
from trapflow.ratelog import CONSOLE_ONCE

log = logging.getLogger(__name__)

#: short names accepted in params; full onnxruntime names are accepted as well
ALIASES = {
    "tensorrt": "TensorrtExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "openvino": "OpenVINOExecutionProvider",
    "coreml": "CoreMLExecutionProvider",
    "dml": "DmlExecutionProvider",
    "rocm": "ROCMExecutionProvider",
    "xnnpack": "XnnpackExecutionProvider",
    "cpu": "CPUExecutionProvider",
}
CPU = "CPUExecutionProvider"
DEFAULT_PROVIDERS = ("tensorrt", "cuda", "cpu")


def provider_name(name: str) -> str:
    """The onnxruntime provider name for a short or full name; WorkerError if unknown."""
    full = ALIASES.get(name.lower())
    if full:
        return full
    if name.endswith("ExecutionProvider"):
        return name
    raise WorkerError(
        f"unknown execution provider {name!r}: expected one of {', '.join(ALIASES)} "
        "or a full onnxruntime name ending in ExecutionProvider"
    )


@dataclass
class Session:
    """A loaded model: the onnxruntime session and what a plugin needs to know about it."""

    session: ort.InferenceSession
    path: Path
    provider: str  # the provider that runs the model
    metadata: dict[str, str]  # custom metadata map (Ultralytics: names, imgsz, stride...)
    model_hash: str = ""  # first 8 hex digits of the file's SHA-256: which model made a result

    @property
    def inputs(self) -> list[ort.NodeArg]:
        """The model's inputs."""
        return list(self.session.get_inputs())

    def input_dtype(self, index: int = 0) -> type[np.floating]:
        """numpy dtype the model expects for input `index` (float32 unless it says float16)."""
        return np.float16 if self.inputs[index].type == "tensor(float16)" else np.float32

    def run(self, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        """Run the model; outputs as numpy arrays."""
        return [np.asarray(o) for o in self.session.run(None, feeds)]


def open_session(
    path: Path, providers: Sequence[str] = DEFAULT_PROVIDERS, threads: int = 1
) -> Session:
    """Load an ONNX model on the first available provider of `providers` (CPU as last resort).

    Logs one line naming the provider used and the ones skipped. WorkerError if the
    file is missing or is not a loadable model.
    """
    wanted = [provider_name(p) for p in providers]
    available = set(ort.get_available_providers())
    usable = [p for p in wanted if p in available]
    skipped = [p for p in wanted if p not in available]
    if CPU not in usable:
        usable.append(CPU)
    if not path.is_file():
        raise WorkerError(f"model file not found: {path}")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    # Spinning threads burn a core each while idle; pools share few cores.
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.log_severity_level = 3
    try:
        session = ort.InferenceSession(str(path), sess_options=opts, providers=usable)
    except Exception as exc:  # onnxruntime raises its own unrelated exception types
        raise WorkerError(f"cannot load ONNX model {path}: {str(exc).strip()[:300]}") from None
    used = session.get_providers()[0]
    if used != (wanted[0] if wanted else CPU):
        # Said once on the console however many models and workers (ONCE, trapflow.log
        # keeps every one); which model runs where is an info line.
        log.warning(
            "ONNX runs on %s (requested %s; not available here: %s)",
            used,
            ", ".join(wanted),
            ", ".join(skipped) or "none",
            extra={CONSOLE_ONCE: True},
        )
    log.info("model %s runs on %s", path.name, used)
    meta = session.get_modelmeta()
    return Session(
        session=session, path=path, provider=used, metadata=dict(meta.custom_metadata_map or {}),
        model_hash=model_hash(path),
    )


def model_hash(path: Path) -> str:
    """Short id of a model file: the first 8 hex digits of its SHA-256 (as `git` shortens)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:8]


class ModelParams(Params):
    """Parameters every ONNX-model plugin takes (its own params add to these)."""

    model: str = ""
    """ONNX file; empty = the plugin's packaged demo model."""
    labels: str = ""
    """Labels file (one per line, or JSON); empty = metadata `names`, else a file beside it."""
    providers: tuple[str, ...] = DEFAULT_PROVIDERS
    """Execution providers in order of preference (tensorrt, cuda, cpu, ...)."""
    threads: Annotated[int, msgspec.Meta(ge=1, le=64)] = 1
    """onnxruntime intra-op threads; 1 so the processes of a pool do not fight over cores."""
