"""Capture's choice when the ring or the broker is busy, as a table: a finite source waits
(lossless replay), a live one drops, and nothing waits once the node is stopping.

Regression: the choice sat inside capture's send loop, testable only with a whole pipeline
and a broker made slow on purpose."""

from __future__ import annotations

import pytest

from trapflow.capture.busy import WAIT_S, Busy, Choice, Drop, Wait, when_busy


@pytest.mark.parametrize(("busy", "finite", "stopping", "want"), [
    # a file or recording waits for a slot, and for the broker: it has no clock to keep
    (Busy.RING, True, False, Wait(WAIT_S)),
    (Busy.BROKER, True, False, Wait(WAIT_S)),
    # a live camera never waits: its next frame is coming; a busy broker's pair gives its
    # written slot back, a pair that found no slot has none to give
    (Busy.RING, False, False, Drop(release=False)),
    (Busy.BROKER, False, False, Drop(release=True)),
    # stopping: nobody will free a slot or read the queue any more, finite or not
    (Busy.RING, True, True, Drop(release=False)),
    (Busy.BROKER, True, True, Drop(release=True)),
    (Busy.RING, False, True, Drop(release=False)),
    (Busy.BROKER, False, True, Drop(release=True)),
])
def test_wait_or_drop(busy: Busy, finite: bool, stopping: bool, want: Choice) -> None:
    assert when_busy(busy, finite=finite, stopping=stopping) == want
