"""onnxruntime session options and provider options from a pool's params."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
import pytest
from trapflow_workers.onnx_session import (
    ModelParams,
    open_session,
    provider_list,
    session_options,
)

from trapflow.errors import WorkerError
from trapflow.plugin import parse_params

MODEL = Path(__file__).resolve().parents[2] / "workers" / "models" / "crab_detector.onnx"


def test_params_reach_the_session_options() -> None:
    p = parse_params({"threads": 2, "inter_threads": 3, "graph_optimization": "basic",
                      "execution_mode": "parallel", "spinning": True}, ModelParams, "mono")
    o = session_options(p)
    assert (o.intra_op_num_threads, o.inter_op_num_threads) == (2, 3)
    assert o.graph_optimization_level == ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
    assert o.execution_mode == ort.ExecutionMode.ORT_PARALLEL
    assert o.get_session_config_entry("session.intra_op.allow_spinning") == "1"


def test_defaults_share_cores_quietly() -> None:
    o = session_options(parse_params({}, ModelParams, "mono"))
    assert (o.intra_op_num_threads, o.inter_op_num_threads) == (1, 1)
    assert o.graph_optimization_level == ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    assert o.execution_mode == ort.ExecutionMode.ORT_SEQUENTIAL
    assert o.get_session_config_entry("session.intra_op.allow_spinning") == "0"
    assert o.get_session_config_entry("session.inter_op.allow_spinning") == "0"


def test_provider_options_go_with_their_provider() -> None:
    got = provider_list(["tensorrt", "cuda", "cpu"], {
        "tensorrt": {"trt_fp16_enable": True, "trt_engine_cache_path": "cache", "device_id": 1},
        "CUDAExecutionProvider": {"device_id": 1}})
    assert got == [
        ("TensorrtExecutionProvider", {"trt_fp16_enable": "True",
                                       "trt_engine_cache_path": "cache", "device_id": "1"}),
        ("CUDAExecutionProvider", {"device_id": "1"}),
        ("CPUExecutionProvider", {}),
    ]


@pytest.mark.parametrize(("params", "match"), [
    ({"graph_optimization": "max"}, r"pools.mono.params.graph_optimization"),
    ({"execution_mode": "async"}, r"pools.mono.params.execution_mode"),
    ({"inter_threads": 0}, r"pools.mono.params.inter_threads"),
    ({"spinning": "yes"}, r"pools.mono.params.spinning"),
    ({"provider_options": {"cuda": "device 0"}}, r"pools.mono.params.provider_options"),
])
def test_bad_session_params_are_rejected(params: dict[str, Any], match: str) -> None:
    with pytest.raises(WorkerError, match=match):
        parse_params(params, ModelParams, "mono")


def test_options_for_a_provider_not_listed_are_rejected() -> None:
    p = parse_params({"providers": ["cpu"], "provider_options": {"cuda": {"device_id": 0}}},
                     ModelParams, "mono")
    with pytest.raises(WorkerError, match="CUDAExecutionProvider, which is not in providers"):
        open_session(MODEL, p.providers, settings=p)


def test_settings_give_the_same_outputs_on_a_real_model() -> None:
    """Optimisation level and threads change how, never what, the model computes."""
    base = open_session(MODEL, ["cpu"])
    tuned = open_session(MODEL, ["cpu"], settings=parse_params(
        {"providers": ["cpu"], "graph_optimization": "disable", "threads": 2,
         "provider_options": {"cpu": {"arena_extend_strategy": "kSameAsRequested"}}},
        ModelParams, "mono"))
    inp = base.inputs[0]
    shape = [d if isinstance(d, int) else 1 for d in inp.shape]
    x = np.random.default_rng(0).random(shape, dtype=np.float32)
    for a, b in zip(base.run({inp.name: x}), tuned.run({inp.name: x}), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4)


def test_a_cpu_only_onnxruntime_falls_back_with_one_info_line(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Regression (issue 22 item 9): every start on a CPU-only machine printed a
    TensorRT/CUDA WARNING although CPU is what such a machine is expected to use."""
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CPUExecutionProvider"])
    with caplog.at_level("INFO", logger="trapflow_workers.onnx_session"):
        s = open_session(MODEL, ("tensorrt", "cuda", "cpu"))
    assert s.provider == "CPUExecutionProvider"
    records = [r for r in caplog.records if r.name.endswith("onnx_session")]
    assert [r.levelname for r in records] == ["INFO"], caplog.text
    assert "not in this onnxruntime: TensorrtExecutionProvider, CUDAExecutionProvider" \
        in records[0].getMessage()
