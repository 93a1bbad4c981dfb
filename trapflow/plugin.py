"""The interface every algorithm implements, with ROS-2-style lifecycle hooks; the plugins'
public API: everything a plugin imports from trapflow comes from this module.

A worker process drives one Worker: configure -> activate -> process()* ->
deactivate -> cleanup -> shutdown. Plugins never see sockets or bytes.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.calibration.rig_files import YAML_FIELDS, read_rig_file
from trapflow.errors import ConfigError, WorkerError
from trapflow.measure.stereo import Measured, Unmeasured, measure, pair_floor
from trapflow.runtime.ratelog import CONSOLE_ONCE
from trapflow.wire.jpeg import reduced_size
from trapflow.wire.messages import (
    Body,
    Detection,
    Extra,
    MonoIR,
    StereoIR,
    StereoPair,
    StereoVO,
    Tag,
    Tags,
)

__all__ = [
    "CONSOLE_ONCE", "YAML_FIELDS", "Body", "ConfigError", "Context", "Detection", "Extra",
    "Measured", "MonoIR", "Pair", "StereoIR", "StereoPair", "StereoRig", "StereoVO", "Tag",
    "Tags", "Unmeasured", "Worker", "WorkerError", "measure", "pair_floor", "read_rig_file",
    "reduced_size",
]


@dataclass(frozen=True)
class Pair:
    """A stereo pair as a plugin sees it: BGR uint8 images, or, for a plugin whose
    needs_images is False, the encoded payload bytes as 1-D uint8 views (zero-copy).

    `reduction` > 1: the images are the frames reduced by that factor (a JPEG decoded at
    a reduced DCT scale for the plugin's max_size), each side ceil(size / reduction); image
    pixel x is frame pixel x * reduction. Raw frames always come at full size (1).
    """

    header: StereoPair
    left: np.ndarray
    right: np.ndarray
    gap: int = 0  # pairs dropped since the previous one this worker saw (ordered pools)
    reduction: int = 1


@dataclass(frozen=True)
class Context:
    """What a plugin may know about where it runs."""

    pool: str
    worker: str
    run_dir: Path
    rig: StereoRig
    debug: bool = False
    save: bool = False
    time: bool = False
    extra: Mapping[str, Any] = field(default_factory=dict)
    #: the side of the AprilTags the source lays, in metres, where the source knows it (a
    #: synthetic world); None for a camera. A plugin's configured size must agree with it
    tag_size_m: float | None = None


class Worker:
    """Base of every algorithm plugin. Override process(); the hooks default to no-ops.

    configure() loads models and checks parameters; raise WorkerError (or any
    exception) there and the node stays inactive with that reason.
    """

    #: whether process() needs decoded images; False skips JPEG decoding entirely
    needs_images: bool = True
    #: whether configure() may be called again, between pairs, with new params: a pool's
    #: parameter change (`trapflow param`) then applies in place (deactivate, configure,
    #: activate) instead of restarting the pool's workers
    reconfigurable: bool = False
    #: the colour process() uses: "bgr" (HxWx3) or "grey". A grey plugin gets a JPEG pair
    #: decoded straight to grey (HxW, about 30 % cheaper); raw frames come as they are
    #: (BGR views of the ring), so it accepts both
    colour: str = "bgr"
    #: the largest image (width, height) process() uses, or None for full frames. A plugin
    #: that shrinks each image to at most this size in both directions (a detector's
    #: letterbox, a classifier's resize) sets it, from its model's input, in configure():
    #: a JPEG pair is then decoded at the largest DCT reduction (1/2, 1/4, 1/8) that still
    #: covers it (trapflow.wire.jpeg.scale_for), which costs a fraction of a full decode, and
    #: Pair.reduction says by how much. Raw frames come at full size whatever it says
    max_size: tuple[int, int] | None = None
    #: the rig a geometric plugin computes with when it is not the run's (its own
    #: `calibration` param); the worker stamps this rig's id on stereo results as `calib`
    rig: StereoRig | None = None

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        """Load models, read parameters. Called once before activate()."""

    def activate(self) -> None:
        """Start accepting pairs."""

    def process(self, pair: Pair) -> Body:
        """Analyse one pair and return one result body."""
        raise NotImplementedError

    def deactivate(self) -> None:
        """Stop accepting pairs; keep loaded resources."""

    def cleanup(self) -> None:
        """Release what configure() loaded."""

    def shutdown(self) -> None:
        """Final hook before the process exits."""
