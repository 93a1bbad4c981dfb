"""Which running pipeline a client of a run directory (`trapflow record`) attaches to.

The run directory must hold a pipeline that runs: one whose supervisor answers on its
control socket. One that is starting (its supervisor holds the directory, and does not
answer yet) is waited for, a bounded time. `runs/latest` (a link that `trapflow start`
moves once its new run captures) that still names a stopped run while a pipeline starts
beside it is waited for too, until the link names the new run: the old run is never taken.
A directory that is not there, or whose pipeline has stopped with none starting, is refused
at once.

`decide` is the pure core (what was seen -> go, wait or refuse); `attach` looks, asks it,
and waits.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from trapflow.errors import StartupError, TrapflowError

POLL_S = 0.5  # between two looks while waiting
ASK_S = 1.0  # how long one status request waits for the supervisor


class Look(NamedTuple):
    """What one look at the run directory saw."""

    named: Path  # the run directory as the command line names it
    target: Path  # the directory it is, links resolved
    is_link: bool  # named through a symbolic link (runs/latest)
    exists: bool
    alive: bool  # a supervisor holds it (its lock file names a live process)
    status: dict[str, Any] | None  # the supervisor's status reply, when it answered
    starting_beside: tuple[Path, ...]  # for a link: other run directories held by a
    # supervisor, one of which will take the link once it captures


class Go(NamedTuple):
    run_dir: Path  # the directory itself (links resolved): later moves of a link do not count
    status: dict[str, Any]


class Wait(NamedTuple):
    say: str  # what is waited for (said once)


class Refuse(NamedTuple):
    why: str


def decide(look: Look, waited_s: float, wait_s: float) -> Go | Wait | Refuse:
    """Go when the pipeline answers; wait (up to wait_s) while one starts; else refuse."""
    where = (f"{look.named} (-> {look.target})" if look.named != look.target
             else str(look.named))
    if look.status is not None:
        return Go(look.target, look.status)
    if look.alive:
        waiting, until = f"the pipeline in {where} is starting", "for it"
    elif look.is_link and look.starting_beside:
        newest = max(look.starting_beside, key=lambda p: p.name)
        waiting = (f"{look.named} names a stopped run ({look.target}) while a pipeline starts "
                   f"in {newest}")
        until = f"for {look.named} to name it"
    elif not look.exists:
        return Refuse(f"no run directory {where}: expected the --run-dir of a running "
                      "pipeline; start it first (trapflow start prints its run directory)")
    else:
        return Refuse(f"no pipeline runs in {where}: its run has stopped; start one first, "
                      "or name the --run-dir of a running one")
    if waited_s >= wait_s:
        return Refuse(f"{waiting}, and no pipeline answered there within {wait_s:g} s; see "
                      "its trapflow.log, or wait longer with --wait")
    return Wait(f"{waiting}; waiting {until} (up to {wait_s:g} s, --wait)")


def look_at(run_dir: Path, ask: Callable[[Path], dict[str, Any]]) -> Look:
    """One look: the directory, its supervisor, and (for a link) the runs starting beside
    it; `ask` sends a status request (StartupError when nothing answers)."""
    from trapflow.supervisor.setup import supervisor_alive

    target = run_dir.resolve()
    exists = target.is_dir()
    alive = exists and supervisor_alive(target)
    status = None
    if alive:
        try:
            status = ask(target)
        except TrapflowError:
            status = None  # starting: its control socket is not up yet
    is_link = run_dir.is_symlink()
    beside: tuple[Path, ...] = ()
    if is_link and not alive:
        try:
            beside = tuple(p for p in run_dir.parent.iterdir()
                           if p.is_dir() and not p.is_symlink() and p != target
                           and supervisor_alive(p))
        except OSError:
            beside = ()
    return Look(run_dir, target, is_link, exists, alive, status, beside)


def attach(run_dir: Path, wait_s: float, say: Callable[[str], None],
           ask: Callable[[Path], dict[str, Any]] | None = None) -> Go:
    """The running pipeline of run_dir, waited for while it starts; StartupError (status
    2) with the one line of `decide` when there is none."""
    if ask is None:
        from trapflow.wire.control_client import request

        def ask(d: Path) -> dict[str, Any]:
            return request(d, "status", ASK_S)

    t0 = time.monotonic()
    said = False
    while True:
        waited_s = time.monotonic() - t0  # up to this look: the first one is never late
        verdict = decide(look_at(run_dir, ask), waited_s, wait_s)
        if isinstance(verdict, Go):
            return verdict
        if isinstance(verdict, Refuse):
            raise StartupError(verdict.why)
        if not said:
            say(verdict.say)
            said = True
        time.sleep(POLL_S)
