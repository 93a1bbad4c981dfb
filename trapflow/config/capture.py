"""Capture: the source of stereo pairs, the rig, and the frames' ring and encoding."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec

from trapflow.config.base import Section as _Section

DEFAULT_JPEG_QUALITY = 90


class SourceConfig(_Section):
    """Where pairs come from and how they are encoded."""

    kind: str = "synthetic"
    """Where pairs come from: synthetic, video, images, v4l2, picamera2, gst or replay (`--source
    KIND:ARGS`; docs/cli.md#sources)."""
    uri: str = ""
    """The kind's location: files, a folder, devices, GStreamer pipelines or a recording (the ARGS
    of `--source KIND:ARGS`); empty for synthetic."""
    rate_hz: Annotated[float, msgspec.Meta(gt=0, le=240)] = 15.0
    """Pairs per second capture produces (a recording at its recorded pace unless replayed with
    `--rate`)."""
    width: Annotated[int, msgspec.Meta(ge=16, le=8192)] = 1280
    """Image width in pixels (of the synthetic world, or asked of a camera)."""
    height: Annotated[int, msgspec.Meta(ge=16, le=8192)] = 720
    """Image height in pixels (of the synthetic world, or asked of a camera)."""
    encoding: Literal["jpeg", "raw"] = "raw"
    """raw: the ring holds the decoded frames and every local pool reads them as they are; jpeg:
    capture encodes each side (~3 ms at 1280x720) and every pool decodes it again."""
    jpeg_quality: Annotated[int, msgspec.Meta(ge=1, le=100)] = DEFAULT_JPEG_QUALITY
    """JPEG quality of pairs on the wire and in recordings (1..100)."""
    seed: int = 1
    """Random seed of the synthetic world (1: crabs walk in after 3 s)."""
    moving: bool = False
    """The synthetic rig moves along a known trajectory."""
    loop: bool = False
    """Start a finite source again when it is exhausted (else the run ends once every pool has
    drained)."""
    options: dict[str, Any] = {}
    """Options of the source kind (e.g. the synthetic world's `tag_size_m`, a replay's `rate`)."""

    @property
    def waits_for_pools(self) -> bool:
        """A finite source read as fast as it goes (a replay at rate 0, not looped) has no
        clock to keep: capture waits for the broker's room in every pool, so the run goes at
        its slowest pool's speed and no pool drops a pair (issue 22, item 2)."""
        if self.loop or self.kind != "replay":
            return False
        try:
            return float(self.options.get("rate", 1.0)) == 0.0
        except (TypeError, ValueError):
            return False  # the source refuses it with its own message


class RigConfig(_Section):
    """The stereo rig: baseline and field of view (or a calibration file)."""

    baseline_m: Annotated[float, msgspec.Meta(gt=0, le=10)] = 0.12
    """Distance between the two cameras in metres, where the source knows none."""
    hfov_deg: Annotated[float, msgspec.Meta(gt=1, lt=179)] = 70.0
    """Horizontal field of view in degrees, where no calibration gives one."""
    calibration: str | None = None
    """Path of a stereo calibration file (docs/calibration.md); it overrides everything else."""


class FramesConfig(_Section):
    """How images travel from capture to the workers on one host."""

    transport: Literal["zmq", "shm"] = "shm"
    """shm: written once into a shared-memory ring, only a descriptor rides on ZeroMQ;
    zmq: the bytes ride in the messages (what remote pools always get)."""
    spare_slots: Annotated[int, msgspec.Meta(ge=0, le=1024)] = 9
    """Ring slots beyond what the pools can hold: pairs between capture and the broker."""
    preroll_slots: Annotated[int, msgspec.Meta(ge=0, le=1024)] = 0
    """Ring slots kept for an event pre-roll."""
