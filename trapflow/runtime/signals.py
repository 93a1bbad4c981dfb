"""Ctrl-C and SIGTERM as a stop flag, for commands whose loop must finish its file cleanly."""

from __future__ import annotations

import signal
import threading


def stop_on_signals() -> threading.Event:
    """An Event set by SIGINT or SIGTERM (the loop checks it and closes what it writes)."""
    stop = threading.Event()

    def handler(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop
