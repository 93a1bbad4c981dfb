"""run.json under a stepped wall clock: started and ended are labels, the duration is
measured. Regression: an NTP fix an hour back mid-run made duration_s -3413."""

from __future__ import annotations

from trapflow.config.schema import Config
from trapflow.supervisor import run_meta

STARTED_NS = 1_764_000_000 * 10**9


def test_duration_is_measured_not_the_labels_difference() -> None:
    ended_ns = STARTED_NS + 187 * 10**9 - 3600 * 10**9  # 187 s later, the clock stepped back
    meta = run_meta.run_metadata(Config(), None, "", STARTED_NS, ended_ns, {},
                                 duration_s=187.04)
    assert meta["duration_s"] == 187.0
    assert meta["started"] == "2025-11-24 16:00:00" and meta["ended"] == "2025-11-24 15:03:07"
