"""The calibrate, record and replay commands: exit codes, one-line errors, clean Ctrl-C."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import zmq
from click.testing import CliRunner
from rosbags.highlevel import AnyReader

from trapflow.calibration.camera import StereoRig
from trapflow.calibration.checkerboard import render_pair
from trapflow.cli.sources import calibrate, lossless_problems, replay
from trapflow.wire.messages import PoolStats, Stats, StereoPair, encode
from trapflow.wire.tap_msgs import TOPIC_IMAGE, TOPIC_RESULT


def test_calibrate_command_writes_yaml(tmp_path: Path) -> None:
    rig = StereoRig.from_fov(480, 360, 65.0, 0.12)
    rng = np.random.default_rng(3)
    for i in range(6):
        tvec = np.array([rng.uniform(-0.15, -0.05), rng.uniform(-0.1, -0.05), 0.6])
        left, right = render_pair(rig, (9, 6), 0.025, rng.uniform(-0.3, 0.3, 3), tvec)
        cv2.imwrite(str(tmp_path / f"l{i}.png"), left)
        cv2.imwrite(str(tmp_path / f"r{i}.png"), right)
    out = tmp_path / "calib.yaml"
    res = CliRunner().invoke(calibrate, [str(tmp_path / "l*.png"), str(tmp_path / "r*.png"),
                                         "--pattern", "9x6", "--square", "0.025", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "RMS reprojection error" in res.output and "views rejected (0)" in res.output
    assert "baseline_m:" in out.read_text()


@pytest.mark.parametrize(
    ("args", "code", "error"),
    [
        (["L*.png", "R*.png", "--pattern", "9by6"], 2, "expected COLSxROWS"),
        (["L*.png", "R*.png", "--square", "0"], 2, "--square"),
        (["nothing*.png", "none*.png"], 1, "no images"),
    ],
)
def test_calibrate_command_errors(args: list[str], code: int, error: str) -> None:
    res = CliRunner().invoke(calibrate, args)
    assert res.exit_code == code and error in res.output


@pytest.mark.parametrize(
    ("args", "code", "error"),
    [
        (["missing.mcap"], 2, "recording not found"),
        (["x.mcap", "--rate", "-1"], 2, "--rate"),
        (["x.mcap", "--loop", "--assert-lossless"], 2, "needs a finite replay"),
        (["x.mcap", "--option", "novalue"], 2, "expected KEY=VALUE"),
    ],
)
def test_replay_command_errors(args: list[str], code: int, error: str) -> None:
    res = CliRunner().invoke(replay, args)
    assert res.exit_code == code and error in res.output, res.output


def test_lossless_problems() -> None:
    full = PoolStats(workers=1, processed=10)
    short = PoolStats(workers=1, processed=8, dropped=2)
    off = PoolStats(workers=0)
    stats = Stats(t_wall_ns=0, uptime_s=1, pairs_in=10, rate_in=1, malformed=0,
                  pools={"mono": full, "vo": short, "tags": off})
    expected = "pool vo: processed 8 of 10 (dropped 2, failed 0, timed out 0, lost 0)"
    assert lossless_problems(10, stats, ["mono", "vo"]) == [expected]
    assert lossless_problems(12, msgspec_replace(stats, pools={"mono": full}), ["mono"])[0] \
        .startswith("read 12 pairs from the recording, 10 entered")
    assert lossless_problems(10, msgspec_replace(stats, pools={"mono": full}), ["mono"]) == []
    assert lossless_problems(10, stats, ["mono"], {"undecodable": 2, "size": 1}) == [
        "3 pairs failed at capture (size 1, undecodable 2)"]


def test_lossless_judges_every_pool_that_ran_though_its_workers_have_stopped() -> None:
    """Regression (issue 12, item 7): the final stats show 0 workers per pool, so the check
    skipped every pool and passed with 130 of 175 pairs dropped and VO failing 40 of 40."""
    stopped = Stats(t_wall_ns=0, uptime_s=9, pairs_in=175, rate_in=0, malformed=0, pools={
        "mono": PoolStats(workers=0, processed=45, dropped=130),
        "vo": PoolStats(workers=0, processed=0, errors=40, lost=135)})
    assert lossless_problems(175, stopped, ["mono", "vo"]) == [
        "pool mono: processed 45 of 175 (dropped 130, failed 0, timed out 0, lost 0)",
        "pool vo: processed 0 of 175 (dropped 0, failed 40, timed out 0, lost 135)"]
    # A pool that ran but never appears in the stats processed nothing.
    assert lossless_problems(175, stopped, ["tags"]) == [
        "pool tags: processed 0 of 175 (dropped 0, failed 0, timed out 0, lost 0)"]


def msgspec_replace(stats: Stats, **kw: object) -> Stats:
    import msgspec

    return msgspec.structs.replace(stats, **kw)


@pytest.mark.timeout(30)
def test_record_command_closes_cleanly_on_ctrl_c(tmp_path: Path) -> None:
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
    pub = ctx.socket(zmq.XPUB)
    pub.setsockopt(zmq.LINGER, 0)
    endpoint = f"ipc://{tmp_path}/tap.sock"
    pub.bind(endpoint)
    out = tmp_path / "rec.mcap"
    code = ("import sys; from trapflow.cli.sources import record; "
            "record(sys.argv[1:], standalone_mode=True)")
    proc = subprocess.Popen([sys.executable, "-c", code, "--endpoint", endpoint, "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        subscribed: set[bytes] = set()
        while subscribed != {TOPIC_IMAGE, TOPIC_RESULT}:
            assert pub.poll(15000), "recorder never subscribed"
            msg = pub.recv()
            subscribed.add(msg[1:])
        jpg = cv2.imencode(".jpg", np.full((32, 32, 3), 90, np.uint8))[1].tobytes()
        for i in range(5):
            h = StereoPair(seq=i, t_wall_ns=10**18 + i, t_mono_ns=i, t_left_ns=i, t_right_ns=i,
                           skew_ns=0, encoding="jpeg", width=32, height=32)
            pub.send_multipart([TOPIC_IMAGE, encode(h), jpg, jpg])
        assert out.with_name("rec.mcap.part").exists()  # mid-recording: only the .part file
        assert not out.exists()
        proc.send_signal(signal.SIGINT)
        output, _ = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        pub.close(linger=0)
    assert proc.returncode == 0, output
    assert out.is_file() and not out.with_name("rec.mcap.part").exists()
    with AnyReader([out]) as reader:  # opens: summary and footer were written
        n = sum(1 for _ in reader.messages())
    pairs = int(output.split(b"rec.mcap: ")[1].split()[0])
    assert n == 3 * pairs  # left, right and pair header for every pair that arrived
