"""The interface every algorithm implements, with ROS-2-style lifecycle hooks; the plugins'
public API: everything a plugin imports from trapflow comes from this module.

A worker process drives one Worker: configure -> activate -> process()* ->
deactivate -> cleanup -> shutdown. Plugins never see sockets or bytes.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import msgspec
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
    "Measured", "MonoIR", "Pair", "Params", "StereoIR", "StereoPair", "StereoRig", "StereoVO",
    "Tag", "Tags", "Unmeasured", "Worker", "WorkerError", "check_frame", "configure_plugin",
    "measure", "pair_floor", "parse_params", "read_rig_file", "reduced_size",
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
    #: the type of the pool's `params:`, a Params Struct: when set, the runtime validates the
    #: pool's params into it (an error names `pools.<pool>.params.<key>` and what was
    #: expected) and configure() gets the Struct instead of the mapping
    params_type: ClassVar[type[Params] | None] = None

    def configure(self, params: Any, ctx: Context) -> None:
        """Load models, read parameters (the mapping of the pool's `params:`, or an instance
        of params_type when the plugin declares one). Called once before activate()."""

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


# --- typed params and the frame check --------------------------------------------------

S = TypeVar("S", bound=msgspec.Struct)


class Params(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Base of every plugin's params Struct: keyword-only, unknown keys rejected."""


_AT = re.compile(r" - at `\$(?P<path>[^`]*)`")
_UNKNOWN = re.compile(r"unknown field `(?P<key>[^`]+)`")


def parse_params(params: Mapping[str, Any], cls: type[S], pool: str) -> S:
    """Validate a pool's params into `cls`; WorkerError names `pools.<pool>.params.<key>`."""
    prefix = f"pools.{pool}.params"
    if not isinstance(params, Mapping):
        raise WorkerError(f"{prefix}: expected a mapping, got {type(params).__name__}")
    try:
        return msgspec.convert(dict(params), cls, strict=True)
    except msgspec.ValidationError as exc:
        text = str(exc)
        at = _AT.search(text)
        path = at.group("path") if at else ""
        unknown = _UNKNOWN.search(text)
        if unknown:
            path += f".{unknown.group('key')}"
            fields = ", ".join(cls.__struct_fields__)
            text = f"unknown key (expected one of: {fields})"
        reason = _AT.sub("", text)
        raise WorkerError(f"{prefix}{path}: {reason}") from None


def check_frame(pair: Pair, size: tuple[int, int] | None = None, what: str = "",
                grey_ok: bool = False) -> None:
    """Raise WorkerError unless both images are HxWx3 uint8 (or HxW with grey_ok) of the
    header's (and `size`'s) size, reduced by pair.reduction (a JPEG decoded at a reduced
    DCT scale for the plugin's max_size)."""
    w, h = pair.header.width, pair.header.height
    iw, ih = reduced_size((w, h), pair.reduction)
    for side, img in (("left", pair.left), ("right", pair.right)):
        if (
            not isinstance(img, np.ndarray)
            or img.dtype != np.uint8
            or not ((img.ndim == 3 and img.shape[2] == 3) or (grey_ok and img.ndim == 2))
        ):
            shape = getattr(img, "shape", None)
            raise WorkerError(
                f"pair {pair.header.seq}: expected a BGR uint8 {side} image, "
                f"got shape {shape} dtype {getattr(img, 'dtype', None)}"
            )
        if img.shape[:2] != (ih, iw):
            at = f" at 1/{pair.reduction}: {iw}x{ih}" if pair.reduction > 1 else ""
            raise WorkerError(
                f"pair {pair.header.seq}: {side} image is "
                f"{img.shape[1]}x{img.shape[0]}, header says {w}x{h}{at}"
            )
    if size is not None and size != (w, h):
        raise WorkerError(
            f"pair {pair.header.seq}: frame is {w}x{h}, expected {size[0]}x{size[1]}"
            f"{' (' + what + ')' if what else ''}"
        )


def configure_plugin(plugin: Worker, params: Mapping[str, Any], ctx: Context) -> None:
    """Configure a plugin as the runtime does: its params validated into its params_type
    when it declares one (WorkerError naming the key), else handed over as given."""
    if plugin.params_type is not None:
        plugin.configure(parse_params(params, plugin.params_type, ctx.pool), ctx)
    else:
        plugin.configure(params, ctx)
