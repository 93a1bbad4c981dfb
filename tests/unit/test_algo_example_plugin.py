"""The documented fifth-algorithm example resolves by import path and returns an Extra."""

from __future__ import annotations

import numpy as np
import pytest

from trapflow import registry
from trapflow.errors import WorkerError
from trapflow.plugin import configure_plugin
from trapflow.testing.kit import make_context, make_pair
from trapflow.wire.messages import Extra, Result, decode_result, encode


def test_example_plugin_by_import_path() -> None:
    cls = registry.resolve("trapflow_workers.example_brightness:Brightness")
    worker = cls()
    configure_plugin(worker, {"dark_below": 50}, make_context(pool="brightness"))
    body = worker.process(make_pair(np.full((48, 64, 3), 30, np.uint8)))
    assert body == Extra(name="brightness", fields={"left": 30.0, "right": 30.0, "dark": True})
    res = Result(
        seq=1, t_wall_ns=0, t_mono_ns=0, pool="brightness", worker="b:0", proc_ns=1, body=body
    )
    assert decode_result(encode(res)).body == body


def test_example_plugin_rejects_unknown_params() -> None:
    worker = registry.resolve("trapflow_workers.example_brightness:Brightness")()
    with pytest.raises(WorkerError, match=r"pools\.brightness\.params\.dark: unknown key"):
        configure_plugin(worker, {"dark": 1}, make_context(pool="brightness"))
