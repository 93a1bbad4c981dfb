"""Outside the wire package, no new module reads a result line by string key: readers decode
lines with trapflow.wire.result_lines and take the Structs' fields (STYLE, 2026-11-28: "a
result read through string keys in many modules"; a renamed key then fails where the line
is decoded, not silently in the thirteenth reader).

The heuristic, on each module's syntax tree: a read of a string constant that is a key of a
result, track or counts line (a field of the Structs, or a result kind), as a subscript
being read (`obj["seq"]`, not `out["seq"] = ...`: the builders write dicts) or as the first
argument of `.get` or `.pop` (`body.get("track")`). Keys other records share (`label`,
`id`, `pool`, `v`, ... in GENERIC) are left out: with them every config, ledger and modem
record read would count. So it finds modules, not every read, and misses a module whose
only reads are of generic keys or through a variable key.

ALLOWED lists the modules that still read by key, each with what it reads: what is left to
move onto the Structs. It may only shrink: a module that no longer reads by key must leave
the list.
"""

from __future__ import annotations

import ast
from pathlib import Path

from trapflow.wire import result_lines as rl

PACKAGE = Path(__file__).resolve().parents[2] / "trapflow"
GENERIC = {"v", "id", "ok", "error", "pool", "model", "calib", "pairs", "labels", "fields",
           "rotation", "translation", "path", "label", "pose", "tags", "counts", "first",
           "inliers"}
ALLOWED = {
    "batch/plan.py": "stitches VO chunks: stereo_vo lines' seq and pose",
    "batch/run.py": "merges chunk lines: mono_ir and stereo_vo lines' seq, timestamp, reinit",
    "cli/status_text.py": "the latest counts interval from status's JSON",
    "events/clips.py": "result lines from the tap: seq and confidence",
    "export/camtrap_obs.py": "detection lines and tracks.jsonl for Camtrap DP observations",
    "export/camtrapdp.py": "result lines' seq and timestamp, tracks' best_confidence",
    "export/check.py": "the surface file's records (the modem's, partial within aggregates); "
                       "the run's own lines are typed",
    "export/report.py": "counts.jsonl intervals, tracks and result lines for the report",
    "modem/codec.py": "the link encoding of the modem's counts records (dwell_s)",
    "modem/sender.py": "records in the outbox: timestamp and confidence of aggregates",
    "modem/thumb.py": "the modem's thumb records (track)",
    "normalizer/node.py": "the builder's dicts it writes: mono_ir items and their track",
    "recording/msgs.py": "result lines to ROS messages: box, confidence, corners",
    "recording/recorder.py": "result lines from the tap: seq and timestamp",
    "recording/vision.py": "detection lines to vision_msgs: box, confidence, track",
    "tracking/review.py": "finished tracks' records for the review queue",
    "tracking/stage.py": "detection items it tracks, track and counts records to modem ones",
    "viewer/state.py": "result lines from the tap for the viewer's state",
}


def _keys() -> set[str]:
    keys = {*rl.KINDS, rl.TRACK_KEY, rl.COUNTS_KEY}
    for cls in (*rl.KINDS.values(), rl.TrackLine, rl.CountsLine, rl.LabelCountLine):
        keys |= set(cls.__struct_fields__)
    return keys - GENERIC


def _reads(tree: ast.AST, keys: set[str]) -> list[tuple[int, str]]:
    out = []
    for node in ast.walk(tree):
        key = None
        if (isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Load)
                and isinstance(node.slice, ast.Constant)):
            key = node.slice.value
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr in ("get", "pop") and node.args
              and isinstance(node.args[0], ast.Constant)):
            key = node.args[0].value
        if isinstance(key, str) and key in keys:
            out.append((node.lineno, key))
    return out


def _readers() -> dict[str, list[tuple[int, str]]]:
    keys = _keys()
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel.startswith("wire/"):
            continue
        if reads := _reads(ast.parse(path.read_text(encoding="utf-8")), keys):
            found[rel] = reads
    return found


def test_no_new_module_reads_a_result_line_by_string_key() -> None:
    new = {m: r[:5] for m, r in _readers().items() if m not in ALLOWED}
    assert not new, ("read result lines through trapflow.wire.result_lines (decode_result, "
                     f"decode_track, decode_counts), not by string key: {new}")


def test_the_allowlist_only_shrinks() -> None:
    gone = sorted(set(ALLOWED) - set(_readers()))
    assert not gone, f"these modules no longer read by string key: take them off ALLOWED: {gone}"


def test_the_heuristic_sees_reads_not_writes() -> None:
    tree = ast.parse('x = body["seq"]\ny = obj.get("track")\nout["range_m"] = 1\nz = c["v"]')
    assert sorted(_reads(tree, _keys())) == [(1, "seq"), (2, "track")]
