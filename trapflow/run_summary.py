"""What a run leaves behind, said at its exit: where the results are, the outbox backlog
still waiting for the modem, the event folders written, and what the source read (a
recording's chosen image topics). Reads the run directory only; never writes."""

from __future__ import annotations

import sqlite3
from pathlib import Path

# Records stored and not yet resolved (acknowledged, expired, aggregated): the same count
# as trapflow.modem.outbox.Outbox.counts(), read without opening the outbox for writing.
_BACKLOG = ("SELECT (SELECT COUNT(*) FROM records) - "
            "(SELECT COUNT(*) FROM resolved JOIN records USING(seq))")


def outbox_backlog(path: Path) -> int | None:
    """Records in the outbox still waiting for the modem; None without an outbox."""
    if not path.is_file():
        return None
    try:
        db = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True, timeout=2.0)
        try:
            return int(db.execute(_BACKLOG).fetchone()[0])
        finally:
            db.close()
    except sqlite3.Error:
        return None


def event_folders(folder: Path) -> int:
    """Event folders written under the events folder."""
    try:
        return sum(1 for p in folder.iterdir() if p.is_dir())
    except OSError:
        return 0


def summary_lines(results: Path, delivered: int, outbox: Path, events: Path | None,
                  source_kind: str, source_where: str) -> list[str]:
    """The exit summary, one line per thing left: results, outbox, events, source."""
    lines = [f"results: {results} ({delivered} results)"]
    backlog = outbox_backlog(outbox)
    if backlog is not None:
        lines.append(f"outbox: {outbox}, {backlog} records still waiting for the modem")
    if events is not None:
        lines.append(f"events: {event_folders(events)} written in {events}")
    if source_kind == "replay" and source_where:
        lines.append(f"replayed: {source_where}")
    return lines
