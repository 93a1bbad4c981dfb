"""Frame sources behind one interface; open_source() picks one from the config."""

from __future__ import annotations

from trapflow.camera import StereoRig
from trapflow.config import SourceConfig
from trapflow.errors import ConfigError
from trapflow.sources.base import Frames, Source, SourceError

__all__ = ["Frames", "Source", "SourceError", "open_source", "KINDS"]

KINDS = ("synthetic",)


def open_source(cfg: SourceConfig, rig: StereoRig) -> Source:
    """Build (not yet open) the source the config names."""
    if cfg.kind == "synthetic":
        from trapflow.sources.synthetic import SyntheticSource

        return SyntheticSource(cfg, rig)
    raise ConfigError(f"source.kind: expected one of {', '.join(KINDS)}, got {cfg.kind!r}")
