"""Kept for callers of the old name: a run's totals now live in trapflow.run_ledger."""

from __future__ import annotations

from trapflow.run_ledger import FAILED_PREFIX, capture_failures, combine, retire, verdict

__all__ = ["FAILED_PREFIX", "capture_failures", "combine", "retire", "verdict"]
