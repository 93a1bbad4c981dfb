"""The source's geometry reaches every node: KITTI calib.txt, CameraInfo in a bag, raw pairs
larger than the config, a calibration that contradicts the frames (issue 12, item 1).

Each run is a real `trapflow start` with real processes, PNG files and bags; the scenes are
rendered with exact homographies from the rig the test chooses (tests.builders.floor_scene).
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from tests.builders import floor_scene, kitti_calib, rectified_calibration
from tests.conftest import REPO, Pipeline, grown, record_until, write_config
from trapflow.calibration.camera import StereoRig
from trapflow.calibration.model import save_calibration
from trapflow.config.schema import from_data
from trapflow.sources.rig import describe

pytestmark = [pytest.mark.timeout(180), pytest.mark.slow]  # starts whole pipelines

# A KITTI-like rig: neither the default size nor the default field of view or baseline.
KITTI = StereoRig(width=752, height=480, fx=436.0, fy=436.0, cx=370.5, cy=235.2,
                  baseline_m=0.110)
BAG = StereoRig(width=640, height=400, fx=402.5, fy=401.0, cx=318.5, cy=201.0,
                baseline_m=0.090)
N = 16
STEP_M = 0.02
HEIGHT_M = 1.2
TAG_ID = 7
TAG_M = 0.24  # 80 texture pixels of 3 mm


def write_kitti(root: Path, rig: StereoRig, n: int) -> None:
    """A KITTI odometry folder: grey PNGs in image_0/ and image_1/, calib.txt, times.txt."""
    pairs, _ = floor_scene(rig, n, STEP_M, HEIGHT_M, TAG_ID, TAG_M)
    for side in ("image_0", "image_1"):
        (root / side).mkdir(parents=True)
    for i, (left, right) in enumerate(pairs):
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), cv2.cvtColor(left, cv2.COLOR_BGR2GRAY))
        cv2.imwrite(str(root / "image_1" / f"{i:06d}.png"),
                    cv2.cvtColor(right, cv2.COLOR_BGR2GRAY))
    (root / "calib.txt").write_text(kitti_calib(rig))
    (root / "times.txt").write_text("".join(f"{i * 0.1:.6e}\n" for i in range(n)))


def ledger(run_dir: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((run_dir / "ledger.json").read_text())
    return data


def tags_config(tmp_path: Path) -> Path:
    """Only the tag's size: the geometry comes from the source (the pool keeps its defaults)."""
    return write_config(tmp_path / "tags.yaml",
                        {"pools": {"tags": {"params": {"tag_size_m": TAG_M}}}})


def check_geometric_results(p: Pipeline, rig: StereoRig, n: int) -> None:
    """Every pair processed by vo and tags, none failed, each result stamped with the rig's id,
    and the numbers are those of that rig: VO's distance and the tag's range match the truth."""
    book = ledger(p.run_dir)
    assert book["produced"] == n
    for pool in ("vo", "tags"):  # tags keeps the latest pair only: it may drop, never fail
        got = book["pools"][pool]
        assert (got["processed"] + got["dropped_by_policy"], got["failed"], got["lost"]) == (
            n, 0, 0), (pool, got)
    assert book["pools"]["vo"]["processed"] == n  # ordered: VO sees every pair
    results = p.results()
    vo = sorted((r["stereo_vo"] for r in results if "stereo_vo" in r), key=lambda r: r["seq"])
    assert len(vo) == n and {r["calib"] for r in vo} == {rig.id}
    assert all(r["ok"] for r in vo[1:])
    travelled = np.linalg.norm(np.array(vo[-1]["pose"])[:, 3])
    # The default field of view (70 deg) and baseline (0.12 m) would be 9 % off or more.
    assert travelled == pytest.approx(STEP_M * (n - 1), rel=0.01)
    tags = [r["tags"] for r in results if "tags" in r]
    assert len(tags) == book["pools"]["tags"]["processed"]
    assert {t["id"] for t in tags} == {TAG_ID}
    assert {t["calib"] for t in tags} == {rig.id}
    for t in tags:  # the camera looks straight down from HEIGHT_M onto the tag at the origin
        x = -STEP_M * (n - 1) / 2 + t["seq"] * STEP_M
        assert np.linalg.norm(t["translation"]) == pytest.approx(np.hypot(x, HEIGHT_M), rel=0.02)


@pytest.mark.parametrize("flags", [[], ["--size", "752x480"]], ids=["no-flags", "size"])
def test_kitti_folder_runs_vo_and_tags_with_its_calib_txt(
    spawn: Callable[..., Pipeline], run_dir: Path, tmp_path: Path, flags: list[str]
) -> None:
    """Regression: a KITTI folder at 752x480 failed every vo and tags pair against the default
    1280x720 rig while capture logged calib.txt's rig, and the run exited 0; with --size, VO
    ran on the configured field of view and baseline instead of calib.txt's."""
    write_kitti(tmp_path / "seq", KITTI, N)
    p = spawn(["--config", str(tags_config(tmp_path)), "--source", f"images:{tmp_path / 'seq'}",
               "--workers", "vo=1,tags=1", "--rate", "10", *flags], run_dir)
    code, _out, err = p.wait(150)
    assert code == 0, err
    check_geometric_results(p, KITTI, N)
    logged = (run_dir / "trapflow.log").read_text()
    assert f"supervisor.shell INFO rig from {tmp_path / 'seq' / 'calib.txt'}: 752x480" in logged
    assert f"(calib {KITTI.id})" in logged


def camera_info(ts: Any, t: int, rig: StereoRig, right: bool) -> Any:
    """A rectified camera's CameraInfo as camera_calibration writes it (P carries -fx*B)."""
    msg = ts.types["sensor_msgs/msg/CameraInfo"]
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"]
    k = rig.K.ravel()
    p = rig.projection(right).ravel()
    return msg(header=stamp_header(ts, t, "right" if right else "left"), height=rig.height,
               width=rig.width, distortion_model="plumb_bob", d=np.zeros(5), k=k,
               r=np.eye(3).ravel(), p=p, binning_x=0, binning_y=0,
               roi=roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def stamp_header(ts: Any, t: int, frame: str) -> Any:
    time_t = ts.types["builtin_interfaces/msg/Time"]
    return ts.types["std_msgs/msg/Header"](
        stamp=time_t(sec=t // 10**9, nanosec=t % 10**9), frame_id=frame)


def write_camera_info_bag(path: Path, rig: StereoRig, n: int) -> None:
    """A ROS 2 bag (written by rosbags) with rectified mono8 images and CameraInfo per camera."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    image = ts.types["sensor_msgs/msg/Image"]
    pairs, _ = floor_scene(rig, n, STEP_M, HEIGHT_M, TAG_ID, TAG_M)
    t0, period = 1_700_000_000_000_000_000, 100_000_000
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {
            name: w.add_connection(f"/stereo/{name}", kind, typestore=ts)
            for name, kind in (("left/image_rect", "sensor_msgs/msg/Image"),
                               ("right/image_rect", "sensor_msgs/msg/Image"),
                               ("left/camera_info", "sensor_msgs/msg/CameraInfo"),
                               ("right/camera_info", "sensor_msgs/msg/CameraInfo"))
        }
        for i, (left, right) in enumerate(pairs):
            t = t0 + i * period
            for side, img in (("left", left), ("right", right)):
                grey = np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
                msg = image(header=stamp_header(ts, t, side), height=rig.height, width=rig.width,
                            encoding="mono8", is_bigendian=0, step=rig.width,
                            data=grey.reshape(-1))
                w.write(conns[f"{side}/image_rect"], t,
                        ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))
                info = camera_info(ts, t, rig, side == "right")
                w.write(conns[f"{side}/camera_info"], t,
                        ts.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))


def test_bag_runs_vo_and_tags_with_its_camera_info(
    spawn: Callable[..., Pipeline], run_dir: Path, tmp_path: Path
) -> None:
    """Regression: a replayed bag at a size other than 1280x720 failed every vo and tags pair;
    its CameraInfo now gives the rig."""
    write_camera_info_bag(tmp_path / "bag", BAG, N)
    p = spawn(["--config", str(tags_config(tmp_path)), "--source", f"replay:{tmp_path / 'bag'}",
               "--workers", "vo=1,tags=1"], run_dir)
    code, _out, err = p.wait(150)
    assert code == 0, err
    check_geometric_results(p, BAG, N)


def digest(left: np.ndarray, right: np.ndarray) -> str:
    """What the digest plugin reports, computed here from the files."""
    h = hashlib.sha1(left.tobytes())
    h.update(right.tobytes())
    return h.hexdigest()[:16]


def test_raw_pairs_larger_than_the_config_all_arrive(
    spawn: Callable[..., Pipeline], run_dir: Path, tmp_path: Path
) -> None:
    """Regression: with --encoding raw the ring was sized from the config (1280x720), so 23 of
    24 larger images were skipped at capture and counted nowhere."""
    n, (w, h) = 6, (1600, 1000)
    rng = np.random.default_rng(11)
    expected = set()
    for side in ("left", "right"):
        (tmp_path / "big" / side).mkdir(parents=True)
    for i in range(n):
        imgs = [cv2.resize(rng.integers(0, 255, (h // 20, w // 20, 3), dtype=np.uint8), (w, h))
                for _ in range(2)]
        for side, img in zip(("left", "right"), imgs, strict=True):
            cv2.imwrite(str(tmp_path / "big" / side / f"{i:03d}.png"), img)
        back = [cv2.imread(str(tmp_path / "big" / s / f"{i:03d}.png")) for s in ("left", "right")]
        expected.add(digest(*back))
    cfg = write_config(tmp_path / "cfg.yaml", {"pools": {"digest": {"policy": "fifo:64"}}})
    p = spawn(["--config", str(cfg), "--source", f"images:{tmp_path / 'big'}", "--encoding", "raw",
               "--workers", "digest=1", "--rate", "10"], run_dir)
    code, _out, err = p.wait(120)
    assert code == 0, err
    got = [r["digest"] for r in p.results() if "digest" in r]
    assert {d["sha1"] for d in got} == expected and len(got) == n
    assert all(d["shape"] == [h, w, 3] for d in got)
    book = ledger(run_dir)
    assert book["produced"] == n and book["pools"]["digest"]["processed"] == n


def test_status_shows_the_rig(spawn: Callable[..., Pipeline], run_dir: Path,
                              tmp_path: Path) -> None:
    write_kitti(tmp_path / "seq", KITTI, 4)
    p = spawn(["--source", f"images:{tmp_path / 'seq'}", "--workers", "vo=1", "--loop",
               "--rate", "5"], run_dir)
    status = p.wait_active(90)
    assert status["rig"]["calib"] == KITTI.id
    assert status["rig"]["fx"] == pytest.approx(KITTI.fx) and status["rig"]["width"] == 752
    assert "calib.txt" in status["rig"]["origin"]
    text = subprocess.run([sys.executable, "-m", "trapflow", "status", "--run-dir", str(run_dir)],
                          capture_output=True, text=True, timeout=30, cwd=REPO).stdout
    assert f"rig calib {KITTI.id}: 752x480, fx 436.0" in text
    code, _out, err = p.stop()
    assert code == 0, err


def test_a_calibration_that_contradicts_the_frames_fails_at_start(
    spawn: Callable[..., Pipeline], run_dir: Path, tmp_path: Path
) -> None:
    """A 1280x720 calibration for 752x480 frames: one line with both sizes and the fix, exit 2,
    instead of every pair failing in every pool."""
    write_kitti(tmp_path / "seq", KITTI, 2)
    save_calibration(rectified_calibration(StereoRig.from_fov(1280, 720, 70.0, 0.12)),
                     tmp_path / "calib.yaml")
    cfg = write_config(tmp_path / "cfg.yaml",
                       {"rig": {"calibration": str(tmp_path / "calib.yaml")}})
    p = spawn(["--config", str(cfg), "--source", f"images:{tmp_path / 'seq'}",
               "--workers", "vo=1"], run_dir)
    code, _out, err = p.wait(60)
    assert code == 2, err
    lines = [line for line in err.splitlines() if "752x480" in line]
    assert len(lines) == 1 and "1280x720" in lines[0] and "calibrate" in lines[0], err


def test_a_recording_keeps_the_rig_for_its_replay(
    spawn: Callable[..., Pipeline], run_dir: Path, tmp_path: Path
) -> None:
    """`trapflow record` writes the running pipeline's rig as CameraInfo beside the images,
    read back with rosbags (ROS 2 tooling's library), so a replay of a 752x480 KITTI run
    computes with calib.txt's rig again, not the configured field of view."""
    write_kitti(tmp_path / "seq", KITTI, 6)
    p = spawn(["--source", f"images:{tmp_path / 'seq'}", "--workers", "vo=1", "--loop",
               "--rate", "10"], run_dir)
    p.wait_active(90)
    out = tmp_path / "field.mcap"
    rcode, rerr = record_until(run_dir, out, grown(lambda: len(p.results()), 20), 40)
    assert rcode == 0, rerr
    code, _out, err = p.stop()
    assert code == 0, err
    with AnyReader([out]) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        info = next(reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                    if c.topic == "/trapflow/right/camera_info")
    assert topics["/trapflow/left/camera_info"] == "sensor_msgs/msg/CameraInfo"
    assert (info.width, info.height) == (752, 480)
    assert -info.p[3] / info.p[0] == pytest.approx(KITTI.baseline_m)
    found = describe(from_data({"source": {"kind": "replay", "uri": str(out)}}))
    assert found.rig.id == KITTI.id and "CameraInfo" in found.origin


def test_a_pair_of_another_size_is_skipped_at_capture(
    spawn: Callable[..., Pipeline], run_dir: Path, tmp_path: Path
) -> None:
    """A pair that contradicts the rig is counted once at capture, with both sizes, instead of
    being sent to fail in every pool."""
    n, odd = 8, 3
    write_kitti(tmp_path / "seq", KITTI, n)
    for side in ("image_0", "image_1"):
        path = tmp_path / "seq" / side / f"{odd:06d}.png"
        cv2.imwrite(str(path), cv2.resize(cv2.imread(str(path)), (640, 400)))
    p = spawn(["--source", f"images:{tmp_path / 'seq'}", "--workers", "vo=1", "--rate", "10"],
              run_dir)
    code, _out, err = p.wait(120)
    assert code == 0, err
    book = ledger(run_dir)
    assert book["produced"] == n - 1
    vo = book["pools"]["vo"]
    assert (vo["processed"], vo["failed"], vo["lost"]) == (n - 1, 0, 0)
    skipped = [line for line in err.splitlines() if "pair skipped" in line]
    assert len(skipped) == 1 and "640x400" in skipped[0] and "752x480" in skipped[0], err
    seqs = sorted(r["stereo_vo"]["seq"] for r in p.results() if "stereo_vo" in r)
    assert seqs == list(range(n - 1))


def test_a_plugins_own_calibration_wins_and_its_id_is_reported(
    spawn: Callable[..., Pipeline], run_dir: Path, tmp_path: Path
) -> None:
    """pools.vo.params.calibration, given explicitly, beats the source's calib.txt for that
    pool, and VO's results name that rig, not the run's."""
    write_kitti(tmp_path / "seq", KITTI, 4)
    own = StereoRig(width=752, height=480, fx=440.0, fy=440.0, cx=376.0, cy=240.0,
                    baseline_m=0.1)
    (tmp_path / "own.yaml").write_text("fx: 440\nfy: 440\ncx: 376\ncy: 240\nbaseline_m: 0.1\n")
    cfg = write_config(tmp_path / "cfg.yaml", {"pools": {
        "vo": {"params": {"calibration": str(tmp_path / "own.yaml")}}}})
    p = spawn(["--config", str(cfg), "--source", f"images:{tmp_path / 'seq'}",
               "--workers", "vo=1", "--rate", "10"], run_dir)
    code, _out, err = p.wait(120)
    assert code == 0, err
    vo = [r["stereo_vo"] for r in p.results() if "stereo_vo" in r]
    assert len(vo) == 4 and {r["calib"] for r in vo} == {own.id} and own.id != KITTI.id
