"""`trapflow status` shows the latest closed interval of counts.jsonl: visits, MaxN and dwell
per label, read from the file's last complete line, or why there is nothing yet."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from trapflow.cli.status_text import counts_text, format_status
from trapflow.supervisor.report import COUNTS_TAIL_BYTES, latest_counts

T0 = 1_795_617_000.0  # 2026-11-25 14:30:00 UTC


def _interval(start_s: float, labels: list[tuple[str, int, int, float]], pairs: int = 9000
              ) -> dict[str, Any]:
    return {"start_s": start_s, "end_s": start_s + 600.0, "pairs": pairs,
            "labels": [{"label": lb, "visits": v, "max_n": n, "dwell_s": d}
                       for lb, v, n, d in labels]}


@pytest.mark.parametrize(("latest", "expected"), [
    # nothing closed yet: say when the first will
    (None, ["counts: no interval closed yet (one every 600 s, counts.jsonl)"]),
    # an interval with effort and no animal
    (_interval(T0, [], pairs=120),
     ["counts 2026-11-25 14:30:00-14:40:00 UTC, 120 pairs seen by the detector: "
      "no animal tracked"]),
    # labels in the file's order, each with its units' header
    (_interval(T0, [("crab", 3, 2, 81.4), ("sea-pen", 1, 1, 5.0)]),
     ["counts 2026-11-25 14:30:00-14:40:00 UTC, 9000 pairs seen by the detector",
      "label              visits     MaxN    dwell",
      "                 (tracks) (tracks)      (s)",
      "crab                    3        2     81.4",
      "sea-pen                 1        1      5.0"]),
])
def test_counts_text(latest: dict[str, Any] | None, expected: list[str]) -> None:
    assert counts_text({"interval_s": 600.0, "latest": latest}) == expected


def test_status_shows_counts_after_the_pools_and_not_without_tracking() -> None:
    reply: dict[str, Any] = {"run_dir": "runs/x", "uptime_s": 3.0, "nodes": [],
                             "counts": {"interval_s": 600.0,
                                        "latest": _interval(T0, [("crab", 3, 2, 81.4)])}}
    text = format_status(reply)
    assert "crab                    3        2     81.4" in text.splitlines()
    assert "counts" not in format_status({**reply, "counts": None})


def _write(path: Path, lines: list[str]) -> Path:
    path.write_text("".join(line + "\n" for line in lines))
    return path


def test_latest_counts_is_the_last_complete_line(tmp_path: Path) -> None:
    first, second = _interval(T0, [("crab", 1, 1, 2.0)]), _interval(T0 + 600, [])
    path = _write(tmp_path / "counts.jsonl", [json.dumps({"counts": first}),
                                              json.dumps({"counts": second})])
    assert latest_counts(path) == second
    # A line the normalizer is still writing is passed over for the one before it.
    with path.open("a") as f:
        f.write('{"counts": {"start_s": 17956')
    assert latest_counts(path) == second


def test_latest_counts_reads_only_the_end_of_a_long_file(tmp_path: Path) -> None:
    filler = json.dumps({"counts": _interval(T0, [("crab", 1, 1, 2.0)])})
    lines = [filler] * (2 * COUNTS_TAIL_BYTES // len(filler))
    last = _interval(T0 + 600, [("fish", 4, 3, 30.0)])
    path = _write(tmp_path / "counts.jsonl", [*lines, json.dumps({"counts": last})])
    assert path.stat().st_size > COUNTS_TAIL_BYTES
    assert latest_counts(path) == last


@pytest.mark.parametrize("content", [None, "", "\n", '{"track": {"id": 1}}\n'])
def test_no_counts_yet(tmp_path: Path, content: str | None) -> None:
    path = tmp_path / "counts.jsonl"
    if content is not None:
        path.write_text(content)
    assert latest_counts(path) is None
