"""onnxruntime sessions for the ONNX plugins: providers in order of preference, with fallback.

Session options come from the pool's params (ModelParams): graph optimisation level,
intra- and inter-op threads, execution mode, thread spinning, and per-provider options
(TensorRT engine cache and fp16, CUDA device id). One intra-op thread and no spinning by
default: a pool runs one session per worker process, and several sessions spinning on
all cores would fight each other.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import msgspec
import numpy as np
import onnxruntime as ort

from trapflow.plugin import CONSOLE_ONCE, Params, WorkerError

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


OptionValue = str | int | float | bool

_GRAPH = {
    "disable": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
    "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
    "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
    "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
}
_MODE = {"sequential": ort.ExecutionMode.ORT_SEQUENTIAL,
         "parallel": ort.ExecutionMode.ORT_PARALLEL}


class SessionSettings(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """How onnxruntime runs a model (the session keys of ModelParams)."""

    threads: Annotated[int, msgspec.Meta(ge=1, le=64)] = 1
    inter_threads: Annotated[int, msgspec.Meta(ge=1, le=64)] = 1
    graph_optimization: Literal["disable", "basic", "extended", "all"] = "all"
    execution_mode: Literal["sequential", "parallel"] = "sequential"
    spinning: bool = False
    provider_options: dict[str, dict[str, OptionValue]] = {}


def session_options(s: SessionSettings | ModelParams) -> ort.SessionOptions:
    """The onnxruntime SessionOptions these settings describe."""
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = s.threads
    opts.inter_op_num_threads = s.inter_threads
    opts.execution_mode = _MODE[s.execution_mode]
    opts.graph_optimization_level = _GRAPH[s.graph_optimization]
    # Spinning threads burn a core each while idle; pools share few cores.
    opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if s.spinning else "0")
    opts.add_session_config_entry("session.inter_op.allow_spinning", "1" if s.spinning else "0")
    opts.log_severity_level = 3
    return opts


def provider_list(names: Sequence[str], options: dict[str, dict[str, OptionValue]]
                  ) -> list[tuple[str, dict[str, str]]]:
    """Providers as (name, options) in order; options keyed by short or full name. WorkerError
    for options of a provider that is not in the list."""
    full = [provider_name(n) for n in names]
    opts = {provider_name(k): v for k, v in options.items()}
    stray = sorted(set(opts) - set(full))
    if stray:
        raise WorkerError(f"provider_options names {', '.join(stray)}, which is not in "
                          f"providers ({', '.join(names)}): add it there or drop its options")
    return [(n, {k: str(v) for k, v in opts.get(n, {}).items()}) for n in full]


def open_session(
    path: Path, providers: Sequence[str] = DEFAULT_PROVIDERS, threads: int = 1,
    settings: SessionSettings | ModelParams | None = None,
) -> Session:
    """Load an ONNX model on the first available provider of `providers` (CPU as last resort).

    `settings` (ModelParams is one) gives the session options and per-provider options;
    without it, `threads` intra-op threads and the defaults. Logs one line naming the
    provider used and the ones skipped. WorkerError if the file is missing or is not a
    loadable model.
    """
    s = settings if settings is not None else SessionSettings(threads=threads)
    wanted = provider_list(providers, s.provider_options)
    available = set(ort.get_available_providers())
    usable = [p for p in wanted if p[0] in available]
    skipped = [p for p, _ in wanted if p not in available]
    if CPU not in [p for p, _ in usable]:
        usable.append((CPU, {}))
    if not path.is_file():
        raise WorkerError(f"model file not found: {path}")
    opts = session_options(s)
    try:
        session = ort.InferenceSession(str(path), sess_options=opts,
                                       providers=[p for p, _ in usable],
                                       provider_options=[o for _, o in usable])
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own unrelated exception types
        raise WorkerError(f"cannot load ONNX model {path}: {str(exc).strip()[:300]}") from None
    used = session.get_providers()[0]
    failed = [p for p, _ in usable if p != CPU and p not in session.get_providers()]
    if failed:
        # A provider this onnxruntime has would not start (driver, device, engine): said
        # once on the console however many models and workers (ONCE, trapflow.log keeps
        # every one).
        log.warning("ONNX runs on %s: %s would not start (see onnxruntime's message above)",
                    used, ", ".join(failed), extra={CONSOLE_ONCE: True})
    # Providers this onnxruntime lacks (a CPU-only machine, the Pi) are expected: one line.
    log.info("model %s runs on %s%s", path.name, used,
             f" (not in this onnxruntime: {', '.join(skipped)})" if skipped else "")
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
    """Parameters every ONNX-model plugin takes (its own params add to these).

    The session keys mirror SessionSettings, so a ModelParams is passed to open_session.
    """

    model: str = ""
    """ONNX file; empty = the plugin's packaged demo model."""
    labels: str = ""
    """Labels file (one per line, or JSON); empty = metadata `names`, else a file beside it."""
    providers: tuple[str, ...] = DEFAULT_PROVIDERS
    """Execution providers in order of preference (tensorrt, cuda, cpu, ...)."""
    threads: Annotated[int, msgspec.Meta(ge=1, le=64)] = 1
    """onnxruntime intra-op threads; 1 so the processes of a pool do not fight over cores."""
    inter_threads: Annotated[int, msgspec.Meta(ge=1, le=64)] = 1
    """onnxruntime inter-op threads (used by execution_mode parallel)."""
    graph_optimization: Literal["disable", "basic", "extended", "all"] = "all"
    """onnxruntime graph optimisation level."""
    execution_mode: Literal["sequential", "parallel"] = "sequential"
    """Run independent branches of the graph one after another or in parallel."""
    spinning: bool = False
    """Let idle onnxruntime threads spin (faster wake-up, a core burnt each); off when
    pools share cores."""
    provider_options: dict[str, dict[str, OptionValue]] = {}
    """Options per provider, keyed by its short or full name, e.g. tensorrt:
    {trt_engine_cache_enable: true, trt_engine_cache_path: cache, trt_fp16_enable: true,
    device_id: 0}, cuda: {device_id: 0}."""
