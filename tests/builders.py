"""Builders for test data in one place: pair headers, encoded pairs, results, the pairs a
source gives, and input files (image folders, trapflow recordings, ROS 2 bags)."""

from __future__ import annotations

import json
import time
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from trapflow.calibration.camera import StereoRig
from trapflow.calibration.model import StereoCalibration
from trapflow.modem.codec import LinkCodec
from trapflow.modem.frame import ACK, DATA, Deframer, data_payload, frame, parse_ack
from trapflow.modem.surface import SurfaceReceiver
from trapflow.recording.recorder import Recorder
from trapflow.sources.base import Frames, SkipPair, Source
from trapflow.wire import messages


def vo_line(reinit: bool = False, ok: bool = True) -> dict[str, Any]:
    """A VO line as the normalizer gives it to the modem (trapflow.normalizer.result_json:
    its results.jsonl line without `pool`), with Rt (when ok) and pose: a small step about a
    skew axis, a pose far from the start (a large turn, metres away)."""
    from trapflow.normalizer.result_json import link_record, normalize

    step = cv2.Rodrigues(np.array([0.0031, -0.0122, 0.0007]))[0]
    pose = np.hstack([cv2.Rodrigues(np.array([0.4, -1.9, 0.25]))[0],
                      [[3.21987], [-0.75432], [12.3457]]])
    body = messages.StereoVO(ok=ok, rotation=tuple(step.ravel()) if ok else (),
                             translation=(0.0123456789, -0.0031234, 0.1987654321),
                             pose=tuple(pose.ravel()), inliers=143 if ok else 3,
                             reinit=reinit, calib="0a1b2c3d")
    line = link_record(normalize(result(body, seq=1234567, t_wall_ns=1_764_000_000_123_000_000,
                                        pool="vo"))[0])
    assert ("Rt" in line["stereo_vo"]) == ok and "pose" in line["stereo_vo"]
    return line


def pair_header(seq: int = 0, width: int = 64, height: int = 48,
                encoding: str = "jpeg") -> messages.StereoPair:
    now = time.monotonic_ns()
    return messages.StereoPair(
        seq=seq, t_wall_ns=time.time_ns(), t_mono_ns=now, t_left_ns=now, t_right_ns=now,
        skew_ns=0, encoding=encoding, width=width, height=height,  # type: ignore[arg-type]
    )


def image(width: int = 64, height: int = 48, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 255, size=(height, width, 3), dtype=np.uint8)


def jpeg(img: np.ndarray, quality: int = 90) -> bytes:
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return buf.tobytes()


def pair_frames(seq: int = 0, width: int = 64, height: int = 48,
                encoding: str = "jpeg") -> list[bytes]:
    """A valid [header, left, right] message."""
    h = pair_header(seq, width, height, encoding)
    left, right = image(width, height, seq), image(width, height, seq + 1)
    if encoding == "raw":
        return [messages.encode(h), left.tobytes(), right.tobytes()]
    return [messages.encode(h), jpeg(left), jpeg(right)]


def result(body: messages.Body, seq: int = 7, t_wall_ns: int = 1751892763120000000,
           pool: str = "mono") -> messages.Result:
    return messages.Result(seq=seq, t_wall_ns=t_wall_ns, t_mono_ns=1, pool=pool,
                           worker=f"{pool}:0:1", proc_ns=1000, body=body)


def floor_scene(rig: StereoRig, n: int, step_m: float = 0.02, height_m: float = 1.2,
                tag_id: int = 7, tag_m: float = 0.25, seed: int = 5
                ) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray]]:
    """n rectified pairs of a textured floor with an AprilTag at the world origin, the rig
    looking straight down and translating step_m per pair along world x; and the poses.

    Rendered through exact homographies with the rig's own K and baseline (tests/kits/scenes.py),
    independently of trapflow's synthetic world.
    """
    from tests.kits.scenes import FloorWorld, looking_down

    world = FloorWorld.square(rig, 4.0, res_m=0.003, seed=seed)
    side = int(round(tag_m / world.res_m))
    marker = cv2.aruco.generateImageMarker(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), tag_id, side)
    quiet = side // 4
    patch = np.full((side + 2 * quiet, side + 2 * quiet), 255, np.uint8)
    # Seen from above, the camera's image axes are the floor's, transposed and reversed.
    patch[quiet:quiet + side, quiet:quiet + side] = marker[::-1, ::-1].T
    c = world.texture.shape[0] // 2 - patch.shape[0] // 2
    world.texture[c:c + patch.shape[0], c:c + patch.shape[1]] = patch
    poses = [looking_down(-step_m * (n - 1) / 2 + i * step_m, 0.0, height_m, 0.0, pitch=0.0)
             for i in range(n)]
    return [world.render(p) for p in poses], poses


def kitti_calib(rig: StereoRig) -> str:
    """A KITTI odometry calib.txt for a rectified rig (P0, P1 as KITTI writes them)."""
    p0 = f"{rig.fx:.6e} 0 {rig.cx:.6e} 0 0 {rig.fy:.6e} {rig.cy:.6e} 0 0 0 1 0"
    p1 = (f"{rig.fx:.6e} 0 {rig.cx:.6e} {-rig.fx * rig.baseline_m:.6e} 0 {rig.fy:.6e} "
          f"{rig.cy:.6e} 0 0 0 1 0")
    return f"P0: {p0}\nP1: {p1}\nP2: {p0}\nP3: {p1}\n"


def rectified_calibration(rig: StereoRig) -> StereoCalibration:
    """A trapflow calibration of an already rectified rig (identity rotations, no distortion)."""
    k = rig.K.tolist()
    q = [[1, 0, 0, -rig.cx], [0, 1, 0, -rig.cy], [0, 0, 0, rig.fx], [0, 0, 1 / rig.baseline_m, 0]]
    return StereoCalibration(
        image_width=rig.width, image_height=rig.height, K1=k, D1=[0.0] * 5, K2=k, D2=[0.0] * 5,
        R=np.eye(3).tolist(), T=[-rig.baseline_m, 0.0, 0.0], R1=np.eye(3).tolist(),
        R2=np.eye(3).tolist(), P1=rig.projection().tolist(), P2=rig.projection(True).tolist(),
        Q=q, baseline_m=rig.baseline_m)


def drain(src: Source, limit: int = 100) -> list[Frames]:
    """Open `src`, read up to `limit` pairs until it ends, close it."""
    src.open()
    try:
        out = []
        while len(out) < limit and (f := src.read()) is not None:
            out.append(f)
        return out
    finally:
        src.close()


def drain_skipping(src: Source, reads: int) -> tuple[list[Frames], list[SkipPair]]:
    """Open `src`, read until it ends, at most `reads` times (a bounded loop: a source that
    retried a bad pair would never end), close it: the pairs read and the pairs skipped."""
    src.open()
    got: list[Frames] = []
    skipped: list[SkipPair] = []
    try:
        for _ in range(reads):
            try:
                f = src.read()
            except SkipPair as exc:
                skipped.append(exc)
                continue
            if f is None:
                break
            got.append(f)
        return got, skipped
    finally:
        src.close()


def small_source(rate_hz: float | None = 15.0, **extra: object) -> dict[str, object]:
    """The `source:` section of most pipeline tests: the synthetic world at 320x240 (cheap to
    render, still large enough for every plugin), at rate_hz (None: the default rate)."""
    out: dict[str, object] = {"width": 320, "height": 240}
    if rate_hz is not None:
        out["rate_hz"] = rate_hz
    return {**out, **extra}


# --- input files: noise pairs in folders and recordings --------------------------------

NOISE_W, NOISE_H = 96, 64  # the size of noise() pairs


def noise(i: int, side: int, w: int = NOISE_W, h: int = NOISE_H) -> np.ndarray:
    """Pair i's image of one side (0 left, 1 right): seeded noise, the same every time."""
    return np.random.default_rng(1000 * side + i).integers(0, 255, (h, w, 3), np.uint8)


def write_folder(root: Path, n: int) -> None:
    """An images source's folder: root/left and root/right with n noise JPEGs each."""
    for side, name in ((0, "left"), (1, "right")):
        (root / name).mkdir(parents=True)
        for i in range(n):
            cv2.imwrite(str(root / name / f"{i:06d}.jpg"), noise(i, side))


def write_recording(path: Path, n: int, chunk: int = 0) -> None:
    """A trapflow recording of n noise pairs; with chunk, a chunk is closed every chunk pairs."""
    with Recorder(path) as rec:
        for i in range(n):
            h = messages.StereoPair(seq=i, t_wall_ns=10**18 + i * 50_000_000, t_mono_ns=i,
                                    t_left_ns=i, t_right_ns=i, skew_ns=0, encoding="jpeg",
                                    width=NOISE_W, height=NOISE_H)
            rec.add_pair(h, cv2.imencode(".jpg", noise(i, 0))[1].tobytes(),
                         cv2.imencode(".jpg", noise(i, 1))[1].tobytes())
            if chunk and i % chunk == chunk - 1:
                rec._writer._writer.flush()


# --- recordings and ROS 2 bags of flat pairs whose level tells their index ----------------

W, H = 64, 48  # the size of img() pairs
T0 = 1_700_000_000_000_000_000  # the first pair's capture time (ns)
PERIOD = 50_000_000  # between pairs (ns)
TS = get_typestore(Stores.ROS2_HUMBLE)


def img(i: int, side: int) -> np.ndarray:
    """Pair i's flat image of one side; level() reads i back, through JPEG too."""
    return np.full((H, W, 3), (10 + 20 * i + 100 * side, 40, 200 - 10 * i), np.uint8)


def level(im: np.ndarray, side: int) -> int:
    """The pair index an img() image of that side was made for."""
    return int(round((float(im[:, :, 0].mean()) - 10 - 100 * side) / 20))


def write_trapflow(path: Path, n: int) -> None:
    """A trapflow recording of n img() pairs, each with a mono_ir result."""
    with Recorder(path) as rec:
        for i in range(n):
            t_mono = 10**9 + i * PERIOD
            h = messages.StereoPair(seq=i, t_wall_ns=T0 + i * PERIOD, t_mono_ns=t_mono,
                                    t_left_ns=t_mono, t_right_ns=t_mono + 3_000_000,
                                    skew_ns=3_000_000, encoding="jpeg", width=W, height=H)
            jl = cv2.imencode(".jpg", img(i, 0))[1].tobytes()
            jr = cv2.imencode(".jpg", img(i, 1))[1].tobytes()
            rec.add_pair(h, jl, jr)
            rec.add_result(f'{{"mono_ir": {{"seq": {i}, "label": "crab"}}}}')


def ros_header(t: int, frame: str) -> Any:
    """A std_msgs/Header stamped t (ns)."""
    Time = TS.types["builtin_interfaces/msg/Time"]  # noqa: N806 - a message class
    Header = TS.types["std_msgs/msg/Header"]  # noqa: N806 - a message class
    return Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id=frame)


def raw_image(t: int, im: np.ndarray, encoding: str = "bgr8") -> Any:
    """A sensor_msgs/Image of `im` (BGR) stamped t, in bgr8 or rgb8."""
    Image = TS.types["sensor_msgs/msg/Image"]  # noqa: N806 - a message class
    data = cv2.cvtColor(im, cv2.COLOR_BGR2RGB) if encoding == "rgb8" else im
    return Image(header=ros_header(t, "cam"), height=H, width=W, encoding=encoding,
                 is_bigendian=0, step=W * 3, data=np.ascontiguousarray(data).reshape(-1))


def write_bag(path: Path, n: int, plugin: StoragePlugin, drop_right: int = -1) -> None:
    """A ROS 2 bag of n img() pairs on two image topics (the right 4 ms late) and an IMU
    topic; pair drop_right has no right image."""
    with Writer(path, version=8, storage_plugin=plugin) as w:
        cl = w.add_connection("/cam0/image_raw", "sensor_msgs/msg/Image", typestore=TS)
        cr = w.add_connection("/cam1/image_raw", "sensor_msgs/msg/Image", typestore=TS)
        other = w.add_connection("/imu", "std_msgs/msg/String", typestore=TS)
        String = TS.types["std_msgs/msg/String"]  # noqa: N806 - a message class
        for i in range(n):
            t = T0 + i * PERIOD
            left = raw_image(t, img(i, 0), "rgb8")
            w.write(cl, t, TS.serialize_cdr(left, "sensor_msgs/msg/Image"))
            if i != drop_right:  # the right camera skips a frame: that pair is lost, not misaligned
                tr = t + 4_000_000
                w.write(cr, tr, TS.serialize_cdr(raw_image(tr, img(i, 1)), "sensor_msgs/msg/Image"))
            w.write(other, t, TS.serialize_cdr(String(data="x"), "std_msgs/msg/String"))


def write_stereo_msg_bag(folder: Path, n: int, right_after_ns: int = 0) -> Path:
    """A bag (folder/bag) of n pairs, each one user-defined message on /stereo:
    trap_msgs/msg/StereoImage (two sensor_msgs/Image), defined in folder/StereoImage.msg
    (returned); each right image is stamped right_after_ns after its left."""
    msgdef = "sensor_msgs/Image left\nsensor_msgs/Image right\n"
    (folder / "StereoImage.msg").write_text(msgdef)
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(msgdef, "trap_msgs/msg/StereoImage"))
    Stereo = store.types["trap_msgs/msg/StereoImage"]  # noqa: N806 - a message class
    with Writer(folder / "bag", version=8) as w:
        c = w.add_connection("/stereo", "trap_msgs/msg/StereoImage", typestore=store)
        for i in range(n):
            t = T0 + i * PERIOD
            m = Stereo(left=raw_image(t, img(i, 0)),
                       right=raw_image(t + right_after_ns, img(i, 1)))
            w.write(c, t, store.serialize_cdr(m, "trap_msgs/msg/StereoImage"))
    return folder / "StereoImage.msg"


# --- stereo VO over a rendered floor ---------------------------------------------------

VO_RIG = StereoRig.from_fov(640, 480, 70.0, 0.12)
VO_PATH_M, VO_STEPS, VO_RADIUS = 2.0, 60, 3.0  # an arc of a circle over the floor


@lru_cache(maxsize=1)
def vo_circle() -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    """The true poses and rendered pairs of VO_RIG along an arc over a textured floor
    (rendered once per test process: it takes seconds)."""
    from tests.kits.scenes import FloorWorld, circle_path

    world = FloorWorld.square(VO_RIG, 2 * VO_RADIUS + 4, res_m=0.004, seed=3)
    poses = list(circle_path(VO_PATH_M, VO_STEPS, VO_RADIUS))
    return poses, [world.render(p) for p in poses]


def vo_plugin(params: dict[str, Any] | None = None) -> Any:
    """The stereo VO plugin configured for VO_RIG (with `params`)."""
    from trapflow_workers.stereo_vo import StereoOdometry

    from trapflow.testing.kit import make_context

    vo = StereoOdometry()
    vo.configure(params or {}, make_context(VO_RIG, pool="vo"))
    return vo


# --- the modem link: a serial-port stand-in and frames of result lines -------------------

SESSION = bytes.fromhex("5e551011")


class BytePort:
    """A serial-port stand-in: bytes put in are read by the receiver, writes are kept."""

    port = "byteport"

    def __init__(self) -> None:
        self.incoming = bytearray()
        self.sent = bytearray()

    @property
    def in_waiting(self) -> int:
        return len(self.incoming)

    def read(self, n: int) -> bytes:
        data = bytes(self.incoming[:n])
        del self.incoming[:n]
        return data

    def write(self, data: bytes) -> int:
        self.sent += data
        return len(data)

    def flush(self) -> None:
        pass

    def acked(self) -> list[int]:
        return [i for kind, p in Deframer().feed(bytes(self.sent)) if kind == ACK
                for i in parse_ack(p)[1]]  # fmt: skip


def scallop(i: int) -> dict[str, Any]:
    """Result line i: a scallop."""
    return {"stereo_ir": {"timestamp": "2025-07-07 12:00:00.000", "seq": i, "label": "scallop",
                          "confidence": 0.9}}  # fmt: skip


def data(floor: int, ids: list[int], session: bytes = SESSION) -> bytes:
    """A DATA frame of the scallop lines `ids` above `floor`, of `session`."""
    codec = LinkCodec()
    return frame(DATA, data_payload(session, floor, [(i, codec.encode(scallop(i))) for i in ids]))


def receive(out_path: Path, state: Path | None,
            *frames: bytes) -> tuple[SurfaceReceiver, BytePort]:
    """A fresh receiver (a fresh surface process) fed these frames, its output closed after."""
    port = BytePort()
    with open(out_path, "ab") as out:
        rx = SurfaceReceiver(port, out, state_path=state)
        for f in frames:
            port.incoming += f
            rx.step()
    return rx, port


def seqs(path: Path) -> list[int]:
    """The seqs of the stereo_ir lines a surface wrote, in order."""
    return [json.loads(line)["stereo_ir"]["seq"] for line in path.read_text().splitlines()]


# --- what a tap carries: numbered pairs and result lines; recordings read back --------------

TAP_W, TAP_H = 96, 64  # the size of tap_jpeg() images
TAP_T_WALL0 = 1_751_892_763_000_000_000  # pair 0's capture time


def tap_jpeg(i: int, side: int) -> bytes:
    """Pair i's JPEG of one side: its number drawn on black."""
    img = np.zeros((TAP_H, TAP_W, 3), np.uint8)
    cv2.putText(img, str(i), (10, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.5, (255, 255, 255 * side), 3)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
    assert ok
    return buf.tobytes()


def tap_header(i: int) -> messages.StereoPair:
    """Pair i's header, 66 ms apart, the left and right exposures before it."""
    t_mono = 5_000_000_000 + i * 66_000_000
    return messages.StereoPair(seq=i, t_wall_ns=TAP_T_WALL0 + i * 66_000_000, t_mono_ns=t_mono,
                               t_left_ns=t_mono - 2_000_000, t_right_ns=t_mono - 1_000_000,
                               skew_ns=1_000_000, encoding="jpeg", width=TAP_W, height=TAP_H,
                               source="test")


def tap_result(algo: str, seq: int) -> bytes:
    """A result line of `algo` for pair seq."""
    body = {"timestamp": "2025-07-07 12:52:43", "seq": seq, "label": "crab", "confidence": 0.71}
    return json.dumps({algo: body}).encode()


def read_mcap(path: Path) -> dict[str, list[tuple[int, object]]]:
    """A recording read back with rosbags: (time, message) per topic, and the topics' types
    under "__types__"."""
    out: dict[str, list[tuple[int, object]]] = {}
    with AnyReader([path]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype)))
    out["__types__"] = [(0, types)]
    return out
