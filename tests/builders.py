"""Builders for test data in one place: pair headers, encoded pairs, results, and the
pairs a source gives."""

from __future__ import annotations

import time
from typing import Any

import cv2
import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.calibration.model import StereoCalibration
from trapflow.sources.base import Frames, SkipPair, Source
from trapflow.wire import messages


def vo_line(reinit: bool = False, ok: bool = True) -> dict[str, Any]:
    """A VO line as the normalizer writes it (trapflow.stages.result_json), with Rt (when ok)
    and pose: a small step about a skew axis, a pose far from the start (a large turn, metres
    away)."""
    from trapflow.stages.result_json import normalize

    step = cv2.Rodrigues(np.array([0.0031, -0.0122, 0.0007]))[0]
    pose = np.hstack([cv2.Rodrigues(np.array([0.4, -1.9, 0.25]))[0],
                      [[3.21987], [-0.75432], [12.3457]]])
    body = messages.StereoVO(ok=ok, rotation=tuple(step.ravel()) if ok else (),
                             translation=(0.0123456789, -0.0031234, 0.1987654321),
                             pose=tuple(pose.ravel()), inliers=143 if ok else 3,
                             reinit=reinit, calib="0a1b2c3d")
    line = normalize(result(body, seq=1234567, t_wall_ns=1_764_000_000_123_000_000,
                            pool="vo"))[0]
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
