"""A recording of a real running pipeline, read back by two independent readers.

rosbags' AnyReader (ROS 2 tooling's library) and the mcap library's reader with its ROS 2
decoder must decode every message of every topic; the counts must match what the run
itself wrote (ledger.json and results.jsonl), and the typed messages (CameraInfo, tf, VO
odometry and path, Foxglove annotations) must carry what the result lines say.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import signal
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader

from tests.conformance.conftest import realdata_root
from tests.conftest import REPO, Pipeline, poll_for
from trapflow.normalizer.result_json import SCHEMA_VERSION

pytestmark = pytest.mark.slow  # starts whole pipelines

W, H = 320, 240


def quat_matrix(q: Any) -> np.ndarray:
    """Rotation matrix of a unit quaternion (the textbook formula, not the recorder's)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def read_rosbags(path: Path) -> tuple[dict[str, str], dict[str, list[Any]]]:
    with AnyReader([path]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        (tf,) = [c for c in reader.connections if c.topic == "/tf_static"]
        # Latched, as rosbag2 records a static transform publisher: replay keeps it.
        (qos,) = tf.ext.offered_qos_profiles  # type: ignore[union-attr]
        assert qos.durability.name == "TRANSIENT_LOCAL" and qos.reliability.name == "RELIABLE"
        msgs: dict[str, list[Any]] = {}
        for conn, _, raw in reader.messages():
            msgs.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    return types, msgs


def read_mcap(path: Path) -> Counter[str]:
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        return Counter(channel.topic for _, channel, _, decoded in reader.iter_decoded_messages()
                       if decoded is not None)


@pytest.mark.timeout(180)
def test_recording_of_a_running_pipeline_decodes_and_matches_its_ledger(
        spawn, run_dir: Path) -> None:
    """Regression (issue 15): `trapflow record` stored no results, since it listened only on
    the broker's tap and results go out on the normalizer's."""
    work = run_dir.parent
    p: Pipeline = spawn(["--workers", "mono=1,vo=1", "--size", f"{W}x{H}", "--rate", "5",
                         "--moving"], run_dir)
    p.wait_active()
    rec = work / "field.mcap"
    # vision_msgs as a sourced ROS 2 has it: a prefix whose share/vision_msgs is the kit's
    # copy (in place); without the kit, no prefix and no Detection2DArray topic.
    env = {k: v for k, v in os.environ.items() if k != "AMENT_PREFIX_PATH"}
    kit = realdata_root() / "vision_msgs" / "4.1.1"
    if kit.is_dir():
        (work / "ros" / "share").mkdir(parents=True)
        (work / "ros" / "share" / "vision_msgs").symlink_to(kit)
        env["AMENT_PREFIX_PATH"] = str(work / "ros")
    recorder = subprocess.Popen(
        [sys.executable, "-m", "trapflow", "record", "--run-dir", str(run_dir), "-o", str(rec)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    part = work / "field.mcap.part"

    def vo_pairs() -> int:
        return sum(1 for x in p.results() if "stereo_vo" in x)

    try:
        poll_for(part.exists, 60, what="the recorder started")
        n0 = vo_pairs()
        poll_for(lambda: vo_pairs() > n0 + 25, 90, what="pairs processed while recording")
        code, _, err = p.stop(signal.SIGINT, timeout=30)  # every result out before we stop
        assert code == 0, err
    finally:
        recorder.send_signal(signal.SIGINT)
        out, err = recorder.communicate(timeout=30)
    assert recorder.returncode == 0, err
    ledger = json.loads((run_dir / "ledger.json").read_text())
    lines = [json.loads(x) for x in (run_dir / "results.jsonl").read_text().splitlines()]

    types, msgs = read_rosbags(rec)
    pairs = [json.loads(m.data) for m in msgs["/trapflow/pairs"]]
    seqs = [h["seq"] for h in pairs]
    s0 = seqs[0]
    # Every pair from the recorder's first to the pipeline's last, none missing.
    assert seqs == list(range(s0, s0 + len(seqs)))
    assert ledger["dropped_at_capture"] == 0 and ledger["failed_at_capture"] == 0
    assert s0 + len(seqs) == ledger["reached_broker"]
    assert "results: " in out and "mono_ir" in out

    assert types == {
        "/trapflow/left/image/compressed": "sensor_msgs/msg/CompressedImage",
        "/trapflow/right/image/compressed": "sensor_msgs/msg/CompressedImage",
        "/trapflow/left/camera_info": "sensor_msgs/msg/CameraInfo",
        "/trapflow/right/camera_info": "sensor_msgs/msg/CameraInfo",
        "/tf_static": "tf2_msgs/msg/TFMessage",
        "/trapflow/pairs": "std_msgs/msg/String",
        "/trapflow/results/mono_ir": "std_msgs/msg/String",
        "/trapflow/results/stereo_vo": "std_msgs/msg/String",
        "/trapflow/vo/odometry": "nav_msgs/msg/Odometry",
        "/trapflow/vo/path": "nav_msgs/msg/Path",
        "/trapflow/left/annotations/mono_ir": "foxglove_msgs/msg/ImageAnnotations",
        **({"/trapflow/left/detections/mono_ir": "vision_msgs/msg/Detection2DArray"}
           if kit.is_dir() else {}),
    }
    n = len(seqs)
    for topic in ("/trapflow/left/image/compressed", "/trapflow/right/image/compressed",
                  "/trapflow/left/camera_info", "/trapflow/right/camera_info"):
        assert len(msgs[topic]) == n, topic

    # Results: exactly the run's own lines for the recorded pairs, per algorithm, and as
    # many pairs processed as the ledger counts once the pairs before the recording are
    # taken away. The two taps' subscriptions land a moment apart: the first two pairs'
    # results may come before the results tap's did, so the count starts after them.
    start = s0 + 2
    for algo, pool in (("mono_ir", "mono"), ("stereo_vo", "vo")):
        mine = [x[algo] for x in lines if algo in x and x[algo]["seq"] >= start]
        recorded = [r for r in (json.loads(m.data)[algo] for m in
                                msgs[f"/trapflow/results/{algo}"]) if r["seq"] >= start]
        assert recorded == mine, algo
        before = {x[algo]["seq"] for x in lines if algo in x and x[algo]["seq"] < start}
        assert len({r["seq"] for r in recorded}) == ledger["pools"][pool]["processed"] - len(before)

    # The mcap library decodes every message of every topic, with the same counts.
    assert read_mcap(rec) == Counter({t: len(v) for t, v in msgs.items()})

    # CameraInfo and tf: the rectified rig, right camera baseline metres along left x.
    left_info = msgs["/trapflow/left/camera_info"][0]
    right_info = msgs["/trapflow/right/camera_info"][0]
    assert (left_info.width, left_info.height) == (W, H)
    fx = left_info.p[0]
    baseline = -right_info.p[3] / fx
    (tf,) = msgs["/tf_static"]
    (t,) = tf.transforms
    assert (t.header.frame_id, t.child_frame_id) == ("trapflow_left", "trapflow_right")
    assert t.transform.translation.x == pytest.approx(baseline, rel=1e-9)
    assert baseline > 0

    # VO: one Odometry per ok result with a pose, equal to it; the Path is the trajectory.
    vo = [json.loads(m.data)["stereo_vo"] for m in msgs["/trapflow/results/stereo_vo"]]
    posed = [r for r in vo if r["ok"] and r.get("pose")]
    assert len(posed) > 10
    odo = msgs["/trapflow/vo/odometry"]
    assert len(odo) == len(posed)
    for r, o in zip(posed, odo, strict=True):
        pose = np.array(r["pose"])
        q = o.pose.pose.orientation
        assert math.isclose(q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2, 1.0, rel_tol=1e-9)
        assert np.allclose(quat_matrix(q), pose[:, :3], atol=2e-3)  # poses carry 3 decimals
        pos = o.pose.pose.position
        assert np.allclose([pos.x, pos.y, pos.z], pose[:, 3])
    (path,) = msgs["/trapflow/vo/path"]
    assert [ps.pose.position.x for ps in path.poses] == [o.pose.pose.position.x for o in odo]

    # Annotations: one message per pair the detector processed, boxes as closed outlines.
    mono = [json.loads(m.data)["mono_ir"] for m in msgs["/trapflow/results/mono_ir"]]
    # Every line carries the schema version; the ONNX detector's, its model file's hash.
    assert {r["v"] for r in mono + vo} == {SCHEMA_VERSION}
    models = {hashlib.sha256(p.read_bytes()).hexdigest()[:8]
              for p in (REPO / "workers" / "models").glob("*.onnx")}
    assert len({r["model"] for r in mono}) == 1 and {r["model"] for r in mono} <= models
    by_seq: dict[int, list[list[float]]] = {}
    for r in mono:
        by_seq.setdefault(r["seq"], [])
        if r["box"]:
            by_seq[r["seq"]].append(r["box"])
    ann = msgs["/trapflow/left/annotations/mono_ir"]
    assert len(ann) == len(by_seq)
    image_stamps = [m.header.stamp for m in msgs["/trapflow/left/image/compressed"]]
    stamp_of = {s: (st.sec, st.nanosec) for s, st in zip(seqs, image_stamps, strict=True)}
    boxes_drawn = 0
    for a, (seq, boxes) in zip(ann, by_seq.items(), strict=True):
        if seq in stamp_of:  # a pair recorded: stamped as its image, so Foxglove syncs them
            assert (a.timestamp.sec, a.timestamp.nanosec) == stamp_of[seq]
        assert len(a.points) == len(a.texts) == len(boxes)
        for pa, (x1, y1, x2, y2) in zip(a.points, boxes, strict=True):
            assert pa.type == 2  # LINE_LOOP
            assert [(pt.x, pt.y) for pt in pa.points] == [(x1, y1), (x2, y1), (x2, y2), (x1, y2)]
            boxes_drawn += 1
    assert boxes_drawn > 0, "the synthetic crabs were never detected while recording"
    if kit.is_dir():  # Detection2DArray: one per pair, each box as its centre and size
        dets = msgs["/trapflow/left/detections/mono_ir"]
        assert len(dets) == len(by_seq)
        for d, (seq, boxes) in zip(dets, by_seq.items(), strict=True):
            if seq in stamp_of:
                assert (d.header.stamp.sec, d.header.stamp.nanosec) == stamp_of[seq]
            got = [v for x in d.detections for v in (
                x.bbox.center.position.x, x.bbox.center.position.y, x.bbox.size_x,
                x.bbox.size_y)]
            assert got == pytest.approx([v for x1, y1, x2, y2 in boxes for v in (
                (x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1)])
