"""The viewer against a replayed recording: the recorded pairs, the pools' charts, the
VO path of a moving rig and the recorded rig's size, seen through the page's JSON."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import Pipeline, poll_for
from tests.integration.viewer_util import free_port, get, get_json, use_token
from trapflow.calibration.camera import StereoRig
from trapflow.recording.recorder import Recorder
from trapflow.synth.render import World
from trapflow.wire.messages import StereoPair

pytestmark = pytest.mark.slow  # starts whole pipelines

W, H, N, RATE = 320, 240, 40, 10.0


def record_synthetic(path: Path) -> None:
    """A recording of a moving rig over the synthetic sea floor, CameraInfo included."""
    rig = StereoRig.from_fov(W, H, 70.0, 0.12)
    world = World(rig, seed=3, moving=True, rate_hz=RATE)
    t0 = time.time_ns()
    with Recorder(path, rig) as rec:
        for i in range(N):
            left, right, _truth = world.render(i)
            t = int(i * 1e9 / RATE)
            h = StereoPair(seq=i, t_wall_ns=t0 + t, t_mono_ns=10**9 + t, t_left_ns=10**9 + t,
                           t_right_ns=10**9 + t, skew_ns=0, encoding="jpeg", width=W, height=H)
            rec.add_pair(h, cv2.imencode(".jpg", left)[1].tobytes(),
                         cv2.imencode(".jpg", right)[1].tobytes())


@pytest.mark.timeout(150)
def test_viewer_shows_a_replayed_recording(spawn, run_dir: Path, tmp_path: Path) -> None:
    rec = tmp_path / "moving.mcap"
    record_synthetic(rec)
    port = free_port()
    p: Pipeline = spawn(["--source", f"replay:{rec}", "--loop", "--workers", "mono=1,vo=1",
                         "--view", str(port)], run_dir)
    p.wait_active(90)
    use_token(port, run_dir)
    url = f"http://127.0.0.1:{port}/api/state"
    state = poll_for(lambda: (s := get_json(url)) and s["frame"] and len(s["vo"]["path"]) >= 10
                     and len(s["pools"].get("vo", {}).get("rate", [])) >= 2 and s,
                     60, interval=0.5, what="a replayed pair, VO path and chart points")
    assert (state["frame"]["width"], state["frame"]["height"]) == (W, H)
    path = np.array(state["vo"]["path"])
    assert np.ptp(path, axis=0).max() > 0.01, "the moving rig's VO path does not move"
    assert state["vo"]["ok_rate"] > 0.5
    assert set(state["pools"]) == {"mono", "vo"}
    code, jpeg = get(f"http://127.0.0.1:{port}/frame/{state['frame']['seq']}/right.jpg")
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert code == 200 and img.shape == (H, W, 3) and img.std() > 5
    code, _, err = p.stop()
    assert code == 0, err
