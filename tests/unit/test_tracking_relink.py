"""The re-link pass over finished tracks: which pieces join (a table), the global choice and
chains, the streaming pass's bounded memory, and `track_rows` / `track_file` with it: a
broken walker written with one id, and the same bytes as without it when nothing joins."""

from __future__ import annotations

from pathlib import Path

import pytest

from trapflow.tracking.motformat import MotRow, format_row, track_file, track_rows
from trapflow.tracking.relink import Piece, RelinkConfig, Relinker, join_cost, link, roots
from trapflow.tracking.tracker import TrackerConfig

CFG = RelinkConfig(max_gap_s=1.0, gate=1.0, gate_per_s=1.0)


def _piece(tid: int, first_s: float, last_s: float, x0: float, vx: float = 100.0,
           label: str = "fish", side: float = 40.0) -> Piece:
    """A box of `side` px moving at vx px/s along y = 100, at x0 at first_s."""
    def box(t: float) -> tuple[float, float, float, float]:
        x = x0 + vx * (t - first_s)
        return (x - side / 2, 80.0, x + side / 2, 80.0 + side)
    return Piece(id=tid, label=label, first_s=first_s, first_box=box(first_s),
                 first_v=(vx, 0.0), last_s=last_s, last_box=box(last_s), last_v=(vx, 0.0))


A = _piece(1, 0.0, 2.0, 0.0)  # ends at x = 200 at 2 s, heading right at 100 px/s
CASES = [
    # (why, later piece, joins)
    ("begins 0.5 s later where A's motion puts it", _piece(2, 2.5, 4.0, 250.0), True),
    ("begins 0.5 s later 30 px off (under a box side)", _piece(2, 2.5, 4.0, 280.0), True),
    ("begins 0.5 s later 100 px off (over 1.5 box sides)", _piece(2, 2.5, 4.0, 350.0),
     False),
    ("the gap is over max_gap_s, even on the predicted spot", _piece(2, 3.5, 5.0, 350.0),
     False),
    ("it begins before A's last box: both overlap in time", _piece(2, 1.9, 4.0, 190.0),
     False),
    ("it begins at A's last box's time", _piece(2, 2.0, 4.0, 200.0), False),
    ("another label", _piece(2, 2.5, 4.0, 250.0, label="crab"), False),
    ("a box three times as large", _piece(2, 2.5, 4.0, 250.0, side=120.0), False),
]


@pytest.mark.parametrize(("why", "b", "joins"), CASES, ids=[c[0] for c in CASES])
def test_which_pieces_join(why: str, b: Piece, joins: bool) -> None:
    assert (join_cost(A, b, CFG) is not None) == joins, why
    assert link([A, b], CFG) == ([(1, 2)] if joins else [])


def test_a_piece_is_never_joined_to_an_earlier_one() -> None:
    b = _piece(2, 2.5, 4.0, 250.0)
    assert join_cost(b, A, CFG) is None


def test_joins_are_chosen_together_not_first_come() -> None:
    # Two fish end side by side, two pieces begin. The first begun fits A2 best, but the
    # second fits only A2: together, the first goes on from A1 and the second from A2.
    a1, a2 = _piece(1, 0.0, 2.0, 0.0), _piece(2, 0.0, 2.0, 40.0)
    b1, b2 = _piece(3, 2.3, 4.0, 262.0), _piece(4, 2.4, 4.0, 300.0)
    assert join_cost(a2, b1, CFG) < join_cost(a1, b1, CFG)  # type: ignore[operator]
    assert join_cost(a1, b2, CFG) is None
    assert link([a1, a2, b1, b2], CFG) == [(1, 3), (2, 4)]


def test_chains_join_to_the_first_piece() -> None:
    a, b, c = _piece(1, 0.0, 1.0, 0.0), _piece(2, 1.5, 2.0, 150.0), _piece(3, 2.5, 3.0, 250.0)
    joins = link([a, b, c], CFG)
    assert joins == [(1, 2), (2, 3)]
    assert roots(joins) == {2: 1, 3: 1}


def test_the_streaming_pass_joins_and_forgets() -> None:
    rl = Relinker(CFG)
    side = 40.0
    for k in range(600):  # 60 s at 10 per s; a fish whose track breaks every 2 s
        t = k / 10
        if k % 20 == 19:
            continue  # one capture time missed: the tracker started a new id after it
        x = 100.0 * t
        rl.add(t, [(1 + k // 20, "fish", (x - side / 2, 80.0, x + side / 2, 80.0 + side))])
        rl.decide(t - 2.0)
        assert rl.held <= 3  # only the pieces that may still be joined
    rl.decide(float("inf"))
    assert rl.joins == 29
    assert rl.id(30) == 1


def _walker_rows(break_at: int, frames: int = 60) -> list[MotRow]:
    """One walker moving right 4 px a frame, detected every frame but `break_at` to
    break_at + 2 where it jumps 24 px further (its tracker loses it)."""
    rows = []
    for f in range(1, frames + 1):
        if break_at <= f < break_at + 3:
            continue
        x = 4.0 * f + (40.0 if f >= break_at else 0.0)
        rows.append(MotRow(frame=f, id=-1, x=x, y=50.0, w=30.0, h=60.0, conf=0.9))
    return rows


def test_track_rows_writes_a_broken_walker_with_one_id() -> None:
    cfg = TrackerConfig(dist_gate=0.0, max_gap_s=0.5)
    dets = _walker_rows(30)
    before = {r.id for r in track_rows(dets, 30.0, cfg)}
    assert len(before) == 2  # the tracker broke it
    after = track_rows(dets, 30.0, cfg, relink=RelinkConfig())
    assert {r.id for r in after} == {min(before)}
    assert [r.frame for r in after] == sorted(r.frame for r in after)


def test_track_file_is_the_same_file_when_nothing_joins(tmp_path: Path) -> None:
    det = tmp_path / "det.txt"
    rows = [MotRow(frame=f, id=-1, x=10.0 + 40 * k + f, y=50.0, w=30.0, h=60.0, conf=0.9)
            for f in range(1, 200) for k in range(3)]
    det.write_text("".join(format_row(r) + "\n" for r in rows))
    plain, linked = tmp_path / "plain.txt", tmp_path / "linked.txt"
    a = track_file(det, plain, 30.0, counts_path=tmp_path / "a.jsonl")
    b = track_file(det, linked, 30.0, counts_path=tmp_path / "b.jsonl",
                   relink=RelinkConfig())
    assert plain.read_bytes() == linked.read_bytes()
    assert (tmp_path / "a.jsonl").read_bytes() == (tmp_path / "b.jsonl").read_bytes()
    assert a == b


def test_track_file_rewrites_the_ids_it_joins(tmp_path: Path) -> None:
    det = tmp_path / "det.txt"
    det.write_text("".join(format_row(r) + "\n" for r in _walker_rows(30)))
    cfg = TrackerConfig(dist_gate=0.0, max_gap_s=0.5)
    out = tmp_path / "out.txt"
    summary = track_file(det, out, 30.0, cfg, relink=RelinkConfig())
    ids = {line.split(",")[1] for line in out.read_text().splitlines()}
    assert ids == {"1"} and summary.tracks == 1
    assert out.read_text().splitlines() == [
        format_row(r) for r in track_rows(_walker_rows(30), 30.0, cfg,
                                               relink=RelinkConfig())]
