"""What a run leaves behind, said at its exit: where the results are, the outbox backlog
still waiting for the modem, the event folders written, and what the source read (a
recording's chosen image topics), read from the run directory once every process stopped."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from trapflow.config.modem import OutboxConfig
from trapflow.errors import TrapflowError
from trapflow.modem.outbox import OutboxQueue


def outbox_backlog(path: Path, cfg: OutboxConfig) -> int | None:
    """Records in the outbox still waiting for the modem (the outbox's own count, read once
    every process that wrote it has stopped); None without an outbox."""
    if not path.is_file():
        return None
    try:
        queue = OutboxQueue(path, cfg)
    except (sqlite3.Error, TrapflowError):
        return None
    try:
        return queue.counts()[2]
    finally:
        queue.close()


def event_folders(folder: Path) -> int:
    """Event folders written under the events folder."""
    try:
        return sum(1 for p in folder.iterdir() if p.is_dir())
    except OSError:
        return 0


def summary_lines(results: Path, delivered: int, outbox: Path, events: Path | None,
                  source_kind: str, source_where: str,
                  outbox_cfg: OutboxConfig | None = None) -> list[str]:
    """The exit summary, one line per thing left: results, outbox, events, source."""
    lines = [f"results: {results} ({delivered} results)"]
    backlog = outbox_backlog(outbox, outbox_cfg or OutboxConfig())
    if backlog is not None:
        lines.append(f"outbox: {outbox}, {backlog} records still waiting for the modem")
    if events is not None:
        lines.append(f"events: {event_folders(events)} written in {events}")
    if source_kind == "replay" and source_where:
        lines.append(f"replayed: {source_where}")
    return lines
