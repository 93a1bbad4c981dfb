"""The run's memory across a power cut: each detector pool's observation state (its live
tracks, the open counting interval, the news already given) saved in the run directory and
restored when a run starts again in it.

Saved atomically (runtime.files.write_atomically) whenever the stage gave something out
(a track ended, an interval closed, news), before it is written or sent, and otherwise at
most every CHECKPOINT_S while pairs come; so after a cut (kill -9, power) the run goes on
with the tracks it had, the surface is not told a label's news twice, and a track ended
before the cut is not written twice. What the last CHECKPOINT_S saw may be tracked again
from the restored state (a track's boxes of those seconds are then missing from it).

Regression (issue 33): over 20 cuts of a run restarting in the same run directory the
surface heard "new label: crab" 21 times, and tracks.jsonl got none of the tracks of the
cut cycles: every live track and the open interval died with each cut.

The state is a pickle of the pools' Observers (the tracker's filters as they are), read
only from the run directory (the owner's alone); a file that does not load (another
version, damaged) is said and set aside, and the run starts with fresh state.
"""

from __future__ import annotations

import logging
import os
import pickle
from pathlib import Path

from trapflow.runtime.files import is_disk_full, write_atomically
from trapflow.tracking.stage import Observer

log = logging.getLogger(__name__)

STATE_FILE = ".observe.state"
CHECKPOINT_S = 5.0
FORMAT = 1  # bumped when the saved shape changes: an older file is set aside


def load(run_dir: Path) -> dict[str, Observer]:
    """The pools' Observers saved in run_dir, each resumed; {} when none was saved."""
    path = run_dir / STATE_FILE
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return {}
    try:
        fmt, observers = pickle.loads(data)
        if fmt != FORMAT or not all(isinstance(o, Observer) for o in observers.values()):
            raise ValueError(f"format {fmt}, expected {FORMAT}")
    except Exception as exc:  # noqa: BLE001  any damage: the run must start, afresh
        aside = path.with_name(path.name + ".unreadable")
        os.replace(path, aside)
        log.warning("observation state %s not restored (%s): set aside as %s; tracks, "
                    "counts and news start afresh", path, exc, aside.name)
        return {}
    for obs in observers.values():
        obs.resume()
    alive = sum(o.tracker.alive for o in observers.values())
    log.info("observation state restored: %d live tracks in %d pools", alive, len(observers))
    return dict(observers)


def save(run_dir: Path, observers: dict[str, Observer]) -> bool:
    """Save the pools' Observers atomically; False when a full disk refused it."""
    try:
        write_atomically(run_dir / STATE_FILE, pickle.dumps((FORMAT, observers)))
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        return False
    return True
