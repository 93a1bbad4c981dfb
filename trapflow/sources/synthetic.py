"""The synthetic source: pairs rendered by the underwater world (trapflow.synth), with truth.

Deterministic from source.seed; capture paces read() at source.rate_hz. Truth poses
are left-camera-to-world, world = left camera of the first pair (OpenCV axes).
"""

from __future__ import annotations

import time

from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import SourceConfig
from trapflow.errors import ConfigError
from trapflow.sources.base import Frames, Geometry, Source
from trapflow.synth.options import parse_options
from trapflow.synth.render import World


def check_source(cfg: SourceConfig, rig: StereoRig) -> None:
    """Reject settings the world cannot honour, naming the parameter."""
    if isinstance(cfg.seed, bool) or not isinstance(cfg.seed, int) or cfg.seed < 0:
        raise ConfigError(f"source.seed: expected a non-negative integer, got {cfg.seed!r}")
    if (rig.width, rig.height) != (cfg.width, cfg.height):
        raise ConfigError(
            f"source.width/height: expected the rig's {rig.width}x{rig.height}, "
            f"got {cfg.width}x{cfg.height}"
        )
    if not 0 < cfg.rate_hz <= 240:
        raise ConfigError(f"source.rate_hz: expected 0 < rate <= 240, got {cfg.rate_hz!r}")


class SyntheticSource(Source):
    """Renders pairs on demand; capture paces them at the configured rate."""

    def __init__(self, cfg: SourceConfig, rig: StereoRig) -> None:
        super().__init__(rig)
        check_source(cfg, rig)
        self.cfg = cfg
        self.options = parse_options(cfg.options)
        self._world: World | None = None
        self._i = 0

    def geometry(self) -> Geometry:
        """The tags' size, where the world lays tags: the run's one tag size."""
        opts = self.options
        return Geometry(tag_size_m=opts.tag_size_m if opts.tags else None)

    def open(self) -> None:
        self._world = World(self.rig, seed=self.cfg.seed, moving=self.cfg.moving,
                            rate_hz=self.cfg.rate_hz, options=self.options)

    @property
    def world(self) -> World:
        """The world (built on first use when open() was not called)."""
        if self._world is None:
            self.open()
        assert self._world is not None
        return self._world

    def read(self) -> Frames:
        left, right, truth = self.world.render(self._i)
        self._i += 1
        now = time.monotonic_ns()
        return Frames(left=left, right=right, t_left_ns=now, t_right_ns=now, truth=truth)
