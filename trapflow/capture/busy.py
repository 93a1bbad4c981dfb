"""Capture's choice when the ring has no free slot or the broker cannot take a pair now:
wait (a file or recording: no clock to keep, so replay is lossless) or drop (a live camera:
its next frame is coming). Pure; trapflow.capture.node carries the choice out."""

from __future__ import annotations

import enum
from dataclasses import dataclass

# How long capture waits before it asks the ring or the broker again: short against a
# frame period, so a finite source resumes as soon as a slot or the queue frees.
WAIT_S = 0.002


class Busy(enum.Enum):
    """What cannot take the pair now."""

    RING = "ring"  # every slot still held by some pool
    BROKER = "broker"  # its queue (or the link to it) is full, or no broker listens


@dataclass(frozen=True)
class Wait:
    """Ask again after `seconds`."""

    seconds: float = WAIT_S


@dataclass(frozen=True)
class Drop:
    """Drop the pair and count it; `release`: its ring slot, written, goes back."""

    release: bool


Choice = Wait | Drop


def when_busy(busy: Busy, *, finite: bool, stopping: bool) -> Choice:
    """Wait while a finite source has the time (not stopping); else drop. A pair dropped
    because the broker was busy was already written to a ring slot, which goes back."""
    if finite and not stopping:
        return Wait()
    return Drop(release=busy is Busy.BROKER)
