"""A small run directory made by hand whose files agree: two crab tracks, one after the
other, on a detector pool and a VO pool of eight pairs each, one counting interval."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

T0 = 1795860000.0  # a multiple of the interval (60 s), UTC
STEP_S = 0.5


def stamp(seq: int) -> str:
    t = T0 + 1 + seq * STEP_S
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(t)) + f".{round(t % 1 * 1000):03d}"


def t_of(seq: int) -> float:
    return T0 + 1 + seq * STEP_S


# seq -> (label, track) of its one detection line; None: a line of nothing seen.
BOXES: dict[int, tuple[str, int | None] | None] = {
    1: None, 2: ("crab", None), 3: ("crab", 1), 4: ("crab", 1), 5: None, 6: ("crab", None),
    7: ("crab", 2), 8: ("crab", 2)}


def results() -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    for seq, box in BOXES.items():
        base = {"timestamp": stamp(seq), "seq": seq}
        if box is None:
            out.append({"mono_ir": {**base, "label": "none", "confidence": 0.0, "box": [],
                                    "v": 2}})
        else:
            out.append({"mono_ir": {**base, "label": box[0], "confidence": 0.8,
                                    "box": [10.0, 10.0, 50.0, 40.0], "track": box[1],
                                    "v": 2}})
        out.append({"stereo_vo": {**base, "ok": True, "inliers": 50, "calib": "0badcafe",
                                  "v": 2}})
    return out


def tracks() -> list[dict[str, Any]]:
    return [{"track": {"id": tid, "label": "crab", "label_share": 1.0,
                       "first_s": round(t_of(a), 3), "last_s": round(t_of(b), 3),
                       "duration_s": round(t_of(b) - t_of(a), 3), "pairs": 3,
                       "best_confidence": 0.8, "best_box": [10.0, 10.0, 50.0, 40.0],
                       "path": [[round(t_of(s), 3), 30.0, 25.0] for s in range(a, b + 1)]}}
            for tid, a, b in ((1, 2, 4), (2, 6, 8))]


def counts() -> list[dict[str, Any]]:
    return [{"counts": {"start_s": T0, "end_s": round(t_of(8), 3), "pairs": 8, "labels": [
        {"label": "crab", "visits": 2, "max_n": 1, "dwell_s": 2.0}]}}]


def ledger() -> dict[str, Any]:
    pool = {"dropped_by_policy": 0, "gated": 0, "failed": 0, "timed_out": 0, "lost": 0,
            "unfinished_at_stop": 0, "processed": 8}
    return {"produced": 8, "pools": {"mono": {**pool, "kinds": ["mono_ir"]},
                                     "vo": {**pool, "kinds": ["stereo_vo"]}}}


def write_lines(path: Path, objs: list[dict[str, Any]]) -> None:
    path.write_text("".join(json.dumps(o) + "\n" for o in objs), encoding="utf-8")


def make_run(run: Path) -> Path:
    """The run directory, written; returns it."""
    run.mkdir(parents=True, exist_ok=True)
    write_lines(run / "results.jsonl", results())
    write_lines(run / "tracks.jsonl", tracks())
    write_lines(run / "counts.jsonl", counts())
    (run / "ledger.json").write_text(json.dumps(ledger()), encoding="utf-8")
    (run / "run.json").write_text(json.dumps({"started": "", "ended": ""}), encoding="utf-8")
    return run
