"""What a run needs before its first process: the run directory (locked), the preflight
(source, rig, plugins, command key), the shared-memory frame ring, and the supervisor's
logging, whose listener owns the PULL of every node's log records (in its own thread).
"""

from __future__ import annotations

import fcntl
import logging
import os
import stat
import sys
from datetime import datetime
from pathlib import Path
from typing import IO

import zmq

from trapflow import registry
from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import Config
from trapflow.errors import StartupError, TrapflowError
from trapflow.gate.policy import gated_pools
from trapflow.runtime.logchannel import LogListener, PrivateRotatingFile
from trapflow.runtime.ratelog import ConsoleOnce
from trapflow.sources import rig
from trapflow.wire.frame_ring import FrameRing, cleanup_stale, ring_slots, slot_capacity

log = logging.getLogger(__name__)

LOCK_FILE = "supervisor.lock"


def default_run_dir(base: Path = Path("runs")) -> Path:
    """A fresh timestamped run directory under ./runs."""
    return base / datetime.now().strftime("%Y%m%d-%H%M%S-%f")[:-3]


def link_latest(run_dir: Path) -> None:
    """Point runs/latest at this run (a convenience: failing to is not an error)."""
    latest = run_dir.parent / "latest"
    try:
        if latest.is_symlink():
            latest.unlink()
        if not latest.exists():
            latest.symlink_to(run_dir.name)
    except OSError:
        pass  # a convenience only


RESERVE_SUFFIX = ".reserve"  # files that only hold disk space for a full disk (runtime.files)


def discard_run_dir(run_dir: Path) -> bool:
    """Remove a run directory that holds nothing of value (its lock file, sockets, empty
    files, the disk space set aside in `*.reserve` files: what a start that failed before
    capture leaves); True if it was removed. One
    with anything else in it (a log that says why a node could not start) is kept."""
    try:
        entries = list(run_dir.iterdir())
        for path in entries:
            st = path.lstat()
            if not (path.name == LOCK_FILE or stat.S_ISSOCK(st.st_mode)
                    or (stat.S_ISREG(st.st_mode)
                        and (st.st_size == 0 or path.name.endswith(RESERVE_SUFFIX)))):
                return False
        for path in entries:
            path.unlink()
        run_dir.rmdir()
    except OSError:
        return False  # a convenience only: a directory left is no error
    return True


def clear_run_dir(run_dir: Path) -> None:
    """At an orderly end, no process of the run left: its socket files and its lock file
    go (removed while still held, so no other start can slip in between). After a crash
    they stay, and the next start in the directory replaces them."""
    try:
        for path in run_dir.iterdir():
            if path.name == LOCK_FILE or stat.S_ISSOCK(path.lstat().st_mode):
                path.unlink(missing_ok=True)
    except OSError as exc:  # a tidy-up only: the run's results are written
        log.debug("could not tidy up %s: %s", run_dir, exc)


def supervisor_alive(run_dir: Path) -> bool:
    """Whether the supervisor holding run_dir runs: its lock file names it (the file is
    gone after an orderly end; after a crash its pid names no process)."""
    try:
        pid = int((run_dir / LOCK_FILE).read_text().strip())
        if pid <= 0:  # a torn write; never a process group
            return False
        os.kill(pid, 0)
    except (OSError, ValueError) as exc:
        return isinstance(exc, PermissionError)  # another user's: alive
    return True


def lock_run_dir(run_dir: Path) -> IO[str]:
    """Hold the run directory for this process (its pid in the lock file) until closed;
    StartupError when another trapflow holds it."""
    f = open(run_dir / LOCK_FILE, "a+")  # noqa: SIM115 - held while running
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.seek(0)
        other = f.read().strip() or "?"
        f.close()
        raise StartupError(
            f"run directory {run_dir} is in use by another trapflow (pid {other})"
        ) from None
    f.seek(0)
    f.truncate()
    f.write(str(os.getpid()))
    f.flush()
    return f


def preflight(c: Config) -> rig.Resolved:
    """Fail before spawning anything when the source or an algorithm cannot load.

    The source, asked without being opened, also tells the rig every node uses
    (trapflow.sources.rig: a calibration file, the source's own, its frame size, the config).
    """
    try:
        found = rig.describe(c)
    except TrapflowError as exc:
        why = str(exc)  # source errors mostly name their kind already
        prefix = "" if why.startswith(f"{c.source.kind}:") else f"{c.source.kind}: "
        raise StartupError(f"source {prefix}{why}") from None
    if c.modem.enabled and c.modem.command_key:  # a bad key file: one line, nothing spawned
        from trapflow.modem.command import load_key

        load_key(c.modem.command_key)
    for pool, pcfg in c.pools.items():
        if pcfg.count > 0:
            try:
                registry.resolve(c.plugin_of(pool))
            except TrapflowError as exc:
                raise StartupError(f"pool {pool!r}: {exc}") from None
    return found


def create_ring(c: Config, stereo: StereoRig | None) -> FrameRing | None:
    """The shared-memory frame ring every local node maps (frames.transport: shm).

    Segments of supervisors that died (kill -9, power cut) are removed first.
    """
    for name in cleanup_stale():
        log.warning("removed stale shared-memory segment %s", name)
    if c.frames.transport != "shm":
        return None
    # A remote pool's pending pairs hold slots too (its remote workers get copies).
    pools = [p for p in c.pools.values() if p.count > 0 or p.remote]
    # A gated pool holds its pre-roll too: pairs the gate keeps until motion or gated.
    kept = sum(g.pre_roll for n, g in gated_pools(c).items()
               if c.pools[n].count > 0 or c.pools[n].remote)
    slots = ring_slots(pools, c.frames.preroll_slots + kept, c.frames.spare_slots)
    # Sized from the rig: capture sends only pairs of the rig's size, so every one fits.
    w, h = stereo.size if stereo is not None else (c.source.width, c.source.height)
    ring = FrameRing.create(slots, slot_capacity(w, h))
    log.info("frame ring %s: %d slots of %d bytes", ring.name, slots, ring.slot_size)
    return ring


class RunLogging:
    """The run's log: trapflow.log (rotating, private) and warnings on stderr, for the
    supervisor's own records and, through the listener's PULL, every node's."""

    def __init__(self, ctx: zmq.Context[zmq.Socket[bytes]], endpoint: str, run_dir: Path,
                 cfg: Config) -> None:
        fmt = logging.Formatter("%(asctime)s %(processName)s %(name)s %(levelname)s %(message)s")
        lcfg = cfg.log_file
        fileh = PrivateRotatingFile(run_dir / "trapflow.log", maxBytes=lcfg.max_bytes,
                                    backupCount=lcfg.backups)
        fileh.setFormatter(fmt)
        errh = logging.StreamHandler(sys.stderr)
        errh.setLevel(logging.WARNING)
        errh.addFilter(ConsoleOnce())  # a warning every worker gives, said once
        errh.setFormatter(logging.Formatter("%(levelname)s %(message)s"))
        # Nodes' records arrive on the log socket; the supervisor's own go straight out.
        self.listener = LogListener(ctx, endpoint, [fileh, errh])
        root = logging.getLogger()
        root.setLevel(cfg.log_level)
        self._root_handlers = root.handlers[:]
        root.handlers[:] = [fileh, errh]
        self.listener.start()

    def stop(self) -> None:
        """Stop the listener (before its context goes), close the handlers, restore the
        root logger's own."""
        self.listener.stop()
        for h in logging.getLogger().handlers:
            h.close()
        logging.getLogger().handlers[:] = self._root_handlers
