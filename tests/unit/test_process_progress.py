"""`trapflow process`'s progress line: rate and ETA from the first finished chunk, counting
the chunks the other workers have in flight during the first wave."""

from __future__ import annotations

import io

import pytest

from trapflow.batch.run import Progress, progress_line

BAR_EMPTY = "[" + "." * 24 + "]"


@pytest.mark.parametrize(
    ("done_chunks", "chunks", "done_pairs", "pairs", "elapsed", "workers", "expected"),
    [
        # nothing finished yet: no rate, no ETA (not a division by zero, not "0.0 pairs/s")
        (0, 12, 0, 96, 3.0, 2, f"{BAR_EMPTY} chunks 0/12  pairs 0/96  - pairs/s  ETA -"),
        # one worker, first chunk of 8 pairs in 2 s: 4 pairs/s, 88 pairs left -> 22 s
        (1, 12, 8, 96, 2.0, 1, "[##......................] chunks 1/12  pairs 8/96  "
                               "4.0 pairs/s  ETA 22s"),
        # two workers, first chunk done in 2 s: the other chunk is as far along, so 8 pairs/s
        # and 11 s left (a rate of 4 would promise 22 s, twice the truth)
        (1, 12, 8, 96, 2.0, 2, "[##......................] chunks 1/12  pairs 8/96  "
                               "8.0 pairs/s  ETA 11s"),
        # first wave over: the plain rate (16 pairs in 2 s)
        (2, 12, 16, 96, 2.0, 2, "[####....................] chunks 2/12  pairs 16/96  "
                                "8.0 pairs/s  ETA 10s"),
        # more workers than chunks: the wave is the chunks, not the workers
        (1, 2, 8, 16, 2.0, 8, "[############............] chunks 1/2  pairs 8/16  "
                              "8.0 pairs/s  ETA 1s"),
        # the end: everything done, ETA 0
        (12, 12, 96, 96, 12.0, 2, "[########################] chunks 12/12  pairs 96/96  "
                                  "8.0 pairs/s  ETA 0s"),
    ],
)
def test_progress_line(done_chunks: int, chunks: int, done_pairs: int, pairs: int,
                       elapsed: float, workers: int, expected: str) -> None:
    assert progress_line(done_chunks, chunks, done_pairs, pairs, elapsed, workers) == expected


def test_a_log_gets_a_line_at_the_start_and_one_at_the_first_chunk() -> None:
    """Regression: the first line came only once a chunk had finished and the next only
    LOG_INTERVAL_S later, so a log showed nothing useful for the first minutes of a run."""
    out = io.StringIO()
    progress = Progress(chunks=3, pairs=24, stream=out, workers=2)
    progress.add(8)
    progress.add(8)  # within LOG_INTERVAL_S of the first: not drawn
    lines = out.getvalue().splitlines()
    assert len(lines) == 2, lines
    assert lines[0].endswith("pairs 0/24  - pairs/s  ETA -")
    assert "pairs 8/24" in lines[1] and "ETA" in lines[1] and "- pairs/s" not in lines[1]
    progress.add(8)  # the last chunk is always drawn
    assert out.getvalue().splitlines()[-1].startswith("[" + "#" * 24 + "] chunks 3/3")
