"""The installed test kit (trapflow.testing): a plugin author runs a plugin on pairs and gets
the lines the normalizer writes, with its params validated as the runtime validates them;
the kit's plugins resolve by name but are never listed to users, and the runtime never
imports the kit."""

from __future__ import annotations

import numpy as np
import pytest

from tests.unit.test_import_graph import import_graph
from trapflow import registry
from trapflow.errors import WorkerError
from trapflow.testing import run_plugin


def _pair(level: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    left = rng.integers(0, 2 * level, (48, 64, 3), dtype=np.uint8)
    right = np.full((48, 64, 3), level, np.uint8)
    return left, right


def test_run_plugin_gives_the_normalizer_lines_of_each_pair() -> None:
    pairs = [_pair(20, 1), _pair(120, 2)]
    lines = run_plugin("brightness", pairs, params={"dark_below": 40})
    assert [line["brightness"]["seq"] for line in lines] == [0, 1]
    for line, (left, right) in zip(lines, pairs, strict=True):
        body = line["brightness"]
        # numpy's own mean of the images, as the example documents its fields
        assert body["left"] == round(float(left.mean()), 1)
        assert body["right"] == round(float(right.mean()), 1)
    assert [line["brightness"]["dark"] for line in lines] == [True, False]


def test_declared_params_are_validated_with_their_yaml_path() -> None:
    with pytest.raises(WorkerError, match=r"pools\.test\.params\.dark_below"):
        run_plugin("brightness", [_pair(20, 1)], params={"dark_below": 999})
    with pytest.raises(WorkerError, match=r"pools\.test\.params\.nope: unknown key"):
        run_plugin("brightness", [_pair(20, 1)], params={"nope": 1})


def test_the_kit_plugins_resolve_but_are_not_listed() -> None:
    for name in registry.TEST_KIT:
        assert registry.resolve(name).__module__ == "trapflow.testing.plugins"
        assert name not in registry.known_names()
    with pytest.raises(WorkerError) as err:
        registry.resolve("no_such_algorithm")
    assert not any(name in str(err.value) for name in ("noop", "flaky", "digest"))


def test_the_runtime_never_imports_the_kit() -> None:
    users = sorted(mod for mod, deps in import_graph().items()
                   if not mod.startswith("trapflow.testing")
                   and any(d.startswith("trapflow.testing") for d in deps))
    assert users == []
