"""Algorithm name -> plugin class. The runtime names workers only through this table.

A pool's `plugin` is a name from BUILTIN, a name published by another package
under the `trapflow.workers` entry-point group, or an import path `module:Class`.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points

from trapflow.errors import WorkerError
from trapflow.plugin import Worker

BUILTIN: dict[str, str] = {
    # The four algorithms a deployment runs (pool names in the default config).
    "mono": "trapflow_workers.crab_detector:CrabDetector",
    "stereo": "trapflow_workers.scene_classifier:SceneClassifier",
    "vo": "trapflow_workers.stereo_vo:StereoOdometry",
    "tags": "trapflow_workers.apriltags:AprilTags",
    # Alternatives, by what they are.
    "crab_detector": "trapflow_workers.crab_detector:CrabDetector",
    "scene_classifier": "trapflow_workers.scene_classifier:SceneClassifier",
    "blob": "trapflow_workers.blob_detector:BlobDetector",
    "histogram": "trapflow_workers.histogram_classifier:HistogramClassifier",
    "flow_vo": "trapflow_workers.flow_vo:FlowOdometry",
    "brightness": "trapflow_workers.example_brightness:Brightness",
}

# The test kit's plugins (trapflow.testing.plugins), by short name for the project's tests and
# benchmarks: resolved like the others, never listed to users (not in known_names()).
TEST_KIT: dict[str, str] = {
    "noop": "trapflow.testing.plugins:Noop",
    "slow": "trapflow.testing.plugins:Slow",
    "crash": "trapflow.testing.plugins:Crash",
    "flaky": "trapflow.testing.plugins:Flaky",
    "flood": "trapflow.testing.plugins:Flood",
    "digest": "trapflow.testing.plugins:Digest",
}

ENTRY_POINT_GROUP = "trapflow.workers"


def known_names() -> list[str]:
    """Every plugin name that resolve() accepts without an import path."""
    names = set(BUILTIN)
    names.update(ep.name for ep in entry_points(group=ENTRY_POINT_GROUP))
    return sorted(names)


def _target(name: str) -> str:
    if ":" in name:
        return name
    if name in BUILTIN:
        return BUILTIN[name]
    if name in TEST_KIT:
        return TEST_KIT[name]
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name == name:
            return str(ep.value)
    raise WorkerError(f"unknown algorithm {name!r}: expected one of {', '.join(known_names())}")


def resolve(name: str) -> type[Worker]:
    """Import and return the Worker class for a plugin name or `module:Class` path."""
    target = _target(name)
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
        cls = getattr(module, attr)
    except (ImportError, AttributeError) as exc:
        raise WorkerError(f"cannot load algorithm {name!r} from {target!r}: {exc}") from exc
    if not (isinstance(cls, type) and issubclass(cls, Worker)):
        raise WorkerError(f"algorithm {name!r}: {target!r} is not a trapflow.plugin.Worker")
    return cls
