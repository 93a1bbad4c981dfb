"""run.json: what a run was, for the reader of its results later (`trapflow report`): the
config (a digest of the whole, a summary of what matters), the versions of trapflow and the
libraries its results depend on, the rig, and when it ran. Built from values passed in; the
supervisor writes it at the end of a run beside ledger.json."""

from __future__ import annotations

import datetime as dt
import hashlib
import platform
from importlib import metadata
from typing import Any

import msgspec

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import Config

# The distributions whose versions change results: the package, its models' runtime, the
# image and geometry code, and the recordings' reader.
VERSIONED = ("trapflow", "numpy", "opencv-python-headless", "onnxruntime", "msgspec",
             "rosbags")


def versions() -> dict[str, str]:
    """Installed versions of VERSIONED and Python ("" for one not installed)."""
    out = {"python": platform.python_version()}
    for name in VERSIONED:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = ""
    return out


def config_digest(cfg: Config) -> str:
    """A short digest of the whole config: two runs with the same digest ran the same."""
    return hashlib.sha256(msgspec.json.encode(cfg)).hexdigest()[:12]


def run_metadata(cfg: Config, rig: StereoRig | None, rig_origin: str, started_ns: int,
                 ended_ns: int, found_versions: dict[str, str],
                 duration_s: float) -> dict[str, Any]:
    """run.json's content: started and ended are wall-clock times in ns since the epoch,
    labels only; duration_s is measured on the monotonic clock (their difference is not
    the run's length when the wall clock stepped: an NTP fix made it -3413 s)."""
    src = cfg.source

    def utc(ns: int) -> str:
        return dt.datetime.fromtimestamp(ns / 1e9, dt.timezone.utc).strftime(
            "%Y-%m-%d %H:%M:%S")

    return {
        "started": utc(started_ns), "ended": utc(ended_ns),
        "duration_s": round(duration_s, 1),
        "config": {
            "digest": config_digest(cfg),
            "source": {"kind": src.kind, "uri": src.uri, "size": f"{src.width}x{src.height}",
                       "rate_hz": src.rate_hz, "loop": src.loop},
            "pools": {name: {"count": p.count, "policy": p.policy,
                             "plugin": cfg.plugin_of(name), "remote": p.remote}
                      for name, p in cfg.pools.items() if p.count > 0 or p.remote},
        },
        "rig": ({"calib": rig.id, "origin": rig_origin, "describe": rig.describe()}
                if rig is not None else None),
        "versions": found_versions,
    }
