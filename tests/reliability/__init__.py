"""The reliability suite: kill storms, power cuts, fuzzing, floods, leaks (issue 16).

Every test runs a short version by default (CI); scripts/chaos.sh runs long versions by
setting the TRAPFLOW_CHAOS_* variables read through scaled(), and collects the figures
the tests report through figures() into one report.
"""

from __future__ import annotations

import json
import os
import time

# Where figures() appends one JSON line per test (set by scripts/chaos.sh); unset: nowhere.
REPORT_ENV = "TRAPFLOW_CHAOS_REPORT"


def scaled(env: str, default: float) -> float:
    """A test's duration or count: the environment's value for env, else the CI default."""
    raw = os.environ.get(env)
    if raw is None or raw == "":
        return default
    try:
        value = float(raw)
    except ValueError:
        raise ValueError(f"{env}: expected a number, got {raw!r}") from None
    if value <= 0:
        raise ValueError(f"{env}: expected a positive number, got {raw!r}")
    return value


def figures(test: str, **values: object) -> None:
    """Record a test's figures (kills, results, losses...) for the chaos report."""
    path = os.environ.get(REPORT_ENV)
    if not path:
        return
    with open(path, "a") as f:
        f.write(json.dumps({"test": test, "at": time.time(), **values}) + "\n")
