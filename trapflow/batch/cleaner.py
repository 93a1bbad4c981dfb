"""multiprocessing's cleaner of named semaphores, started before the local Dask cluster and
in a session of its own, so that a kill -9 of `trapflow process`'s whole process group does
not take it along.

Why: the local cluster's nannies start their workers with multiprocessing's `spawn`, whose
locks are POSIX named semaphores (`/dev/shm/sem.mp-*`); multiprocessing's resource tracker
unlinks them when the processes using them are gone. Started lazily, as a child in the
caller's process group, it died with a kill of the group and 12 semaphores stayed in
/dev/shm for good (issue 36 item 7). Started here, it outlives the kill by the moment it
takes to see its pipe close, unlinks what is left, and exits: nothing of the run outlives
it, and trapflow never has to guess which semaphores of /dev/shm were its own.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from multiprocessing import resource_tracker, util


def _spawn_in_own_session(path: str, args: Sequence[str], passfds: Sequence[int]) -> int:
    """multiprocessing.util.spawnv_passfds, the child in a new session (setsid)."""
    for fd in passfds:
        os.set_inheritable(fd, True)
    return os.posix_spawn(path, list(args), dict(os.environ), setsid=True)


def start_cleaner() -> None:
    """Start this process's resource tracker now, in its own session (a no-op when it
    runs already: the cluster's processes and this one then share it)."""
    spawn = util.spawnv_passfds
    util.spawnv_passfds = _spawn_in_own_session  # type: ignore[assignment]
    try:
        resource_tracker.ensure_running()
    finally:
        util.spawnv_passfds = spawn
