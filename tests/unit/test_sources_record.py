"""Recording without a tap: raw pairs become JPEG, bad result lines and an unwritable
output are one clear error, results that come before their pair (the tap-fed recorder is in
tests/integration/test_sources_record.py)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.builders import TAP_H as H
from tests.builders import TAP_T_WALL0 as T_WALL0
from tests.builders import TAP_W as W
from tests.builders import read_mcap as read_back
from tests.builders import tap_header as header
from tests.builders import tap_jpeg as jpeg
from trapflow.recording.recorder import TOPIC_LEFT, Recorder, RecorderError
from trapflow.wire.messages import StereoPair


def test_raw_pairs_are_recorded_as_jpeg(tmp_path: Path) -> None:
    img = np.full((H, W, 3), 128, np.uint8)
    h = StereoPair(seq=0, t_wall_ns=T_WALL0, t_mono_ns=1, t_left_ns=1, t_right_ns=1, skew_ns=0,
                   encoding="raw", width=W, height=H)
    with Recorder(tmp_path / "raw.mcap") as rec:
        rec.add_pair(h, img.tobytes(), img.tobytes())
    got = read_back(tmp_path / "raw.mcap")
    data = bytes(got[TOPIC_LEFT][0][1].data)  # type: ignore[attr-defined]
    dec = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert abs(float(dec.mean()) - 128) < 2


@pytest.mark.parametrize(
    ("line", "error"),
    [
        (b"not json", "expected one JSON object"),
        (b"[1, 2]", "expected one {algorithm"),
        (b'{"a": {}, "b": {}}', "expected one {algorithm"),
        (b'{"bad name": {"seq": 1}}', "expected an algorithm name"),
    ],
)
def test_bad_result_lines_are_rejected(tmp_path: Path, line: bytes, error: str) -> None:
    with Recorder(tmp_path / "r.mcap") as rec, pytest.raises(RecorderError, match=error):
        rec.add_result(line)


def test_unwritable_output_is_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(RecorderError, match="cannot write recording"):
        Recorder(tmp_path / "no" / "such" / "dir" / "x.mcap")


def test_results_ahead_of_their_pair_take_its_capture_time_and_order(tmp_path: Path) -> None:
    """Regression: under load a result reached the recorder before its pair (images come
    through their own tap connection) and was stamped with its receive time, so readers
    sorted it after later results and Foxglove could not draw it on its image."""
    lines = [json.dumps({"mono_ir": {"timestamp": "2025-07-07 12:52:43.120", "seq": seq,
                                     "label": "crab", "confidence": c}}).encode()
             for seq, c in ((0, 0.9), (0, 0.5), (1, 0.8), (2, 0.7))]
    with Recorder(tmp_path / "early.mcap") as rec:
        rec.add_result(lines[0])  # seq 0's lines before pair 0
        rec.add_result(lines[1])
        rec.add_pair(header(0), jpeg(0, 0), jpeg(0, 1))
        rec.add_result(lines[2])  # seq 1's line; pair 1 never comes (the tap dropped it)
        rec.add_pair(header(2), jpeg(2, 0), jpeg(2, 1))
        rec.add_result(lines[3])  # seq 2's line after its pair, as usual
    got = read_back(tmp_path / "early.mcap")
    recorded = [(t, json.loads(m.data)["mono_ir"])  # type: ignore[attr-defined]
                for t, m in got["/trapflow/results/mono_ir"]]
    assert [(b["seq"], b["confidence"]) for _, b in recorded] == [
        (0, 0.9), (0, 0.5), (1, 0.8), (2, 0.7)]
    # A pair's results at its capture time (t_wall_ns, the left image's stamp).
    assert recorded[0][0] == recorded[1][0] == header(0).t_wall_ns
    assert recorded[2][0] == 1_751_892_763_120_000_000  # its own timestamp: no pair to take
    assert recorded[3][0] == header(2).t_wall_ns
