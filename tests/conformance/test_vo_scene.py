"""Stereo VO on a scene trapflow did not make: a pitched rig turning over a rocky sea floor.

The frames come from tests/conformance/vo_scene.py (its own ray caster, not trapflow's renderer).
trapflow's VO gets the scene's rig as a source would give it and nothing else. Its drift is held
to the targets and compared with a plain frame-to-frame reference written here: Shi-Tomasi corners,
stereo depth by pyramidal KLT along the rectified rows, KLT into the next left image, PnP RANSAC.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from trapflow_workers.stereo_vo import StereoOdometry

from tests.conformance import vo_scene
from trapflow.calibration.camera import StereoRig
from trapflow.testing.kit import make_context, make_pair

# The first test also waits for the render (about 150 s of CPU on a loaded CI machine).
pytestmark = pytest.mark.timeout(480)

SEGMENTS_M = (2.0, 4.0, 6.0, 8.0)
MAX_DRIFT_PCT = 0.5  # translational, % of distance travelled
MAX_DRIFT_DEG_PER_M = 0.05  # rotational
CORNERS = 500  # the reference tracks as many corners as trapflow does by default


@pytest.fixture(scope="session")
def scene_frames(pytestconfig: pytest.Config, tmp_path_factory: pytest.TempPathFactory
                 ) -> dict[str, tuple[list[np.ndarray], list[Path]]]:
    """Both sequences as PNG pairs, rendered once and kept in pytest's cache folder under the
    hash of the renderer's source (rendering takes about a minute on two cores); in a
    temporary folder when the cache is switched off."""
    key = hashlib.sha256(Path(vo_scene.__file__).read_bytes()).hexdigest()[:16]
    store = getattr(pytestconfig, "cache", None)  # absent with -p no:cacheprovider
    if store is not None:
        cache = store.mkdir(f"vo_scene_{key}")
    else:
        cache = tmp_path_factory.mktemp("vo_scene")
    return {name: vo_scene.sequence(name, cache) for name in vo_scene.SEQUENCES}


def _inv(t: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def _angle_deg(r: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(r)) - 1) / 2))))


def drift(truth: list[np.ndarray], est: list[np.ndarray], every: int = 5) -> tuple[float, float]:
    """KITTI-style drift: over every segment of SEGMENTS_M metres (starting every `every`
    frames), the error of the estimated relative motion; mean translation error in % of the
    segment length and mean rotation error in degrees per metre."""
    centres = np.array([p[:3, 3] for p in truth])
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))])
    terr, rerr = [], []
    for first in range(0, len(truth), every):
        for length in SEGMENTS_M:
            after = np.flatnonzero(dist >= dist[first] + length)
            if after.size == 0:
                continue
            last = int(after[0])
            err = _inv(_inv(est[first]) @ est[last]) @ (_inv(truth[first]) @ truth[last])
            terr.append(np.linalg.norm(err[:3, 3]) / length)
            rerr.append(_angle_deg(err[:3, :3]) / length)
    assert terr, "the path is shorter than every segment"
    return 100 * float(np.mean(terr)), float(np.mean(rerr))


def _grey(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def _klt(a: np.ndarray, b: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal KLT a -> b with a forward-backward check (0.5 px)."""
    lk = {"winSize": (21, 21), "maxLevel": 4,
          "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}
    fwd, st, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, None, **lk)
    back, st_b, _ = cv2.calcOpticalFlowPyrLK(b, a, fwd, None, **lk)
    ok = st.ravel().astype(bool) & st_b.ravel().astype(bool)
    ok &= np.linalg.norm((back - pts).reshape(-1, 2), axis=1) < 0.5
    return fwd.reshape(-1, 2), ok


def reference_vo(rig: StereoRig, frames: list[Path]) -> list[np.ndarray]:
    """Plain frame-to-frame stereo VO: camera-to-first-camera poses, one per pair."""
    poses = [np.eye(4)]
    prev_l, prev_r = (_grey(x) for x in vo_scene.load_pair(frames[0]))
    for f in frames[1:]:
        left, right = (_grey(x) for x in vo_scene.load_pair(f))
        pts = cv2.goodFeaturesToTrack(prev_l, CORNERS, 0.01, 8, blockSize=7).astype(np.float32)
        in_right, ok_r = _klt(prev_l, prev_r, pts)
        p = pts.reshape(-1, 2)
        disp = p[:, 0] - in_right[:, 0]
        ok_r &= (np.abs(in_right[:, 1] - p[:, 1]) < 1.0) & (disp > 0.5)
        z = rig.fx * rig.baseline_m / np.where(ok_r, disp, 1.0)
        xyz = np.column_stack([(p[:, 0] - rig.cx) * z / rig.fx, (p[:, 1] - rig.cy) * z / rig.fy, z])
        nxt, ok_t = _klt(prev_l, left, pts)
        use = ok_r & ok_t
        found, rvec, tvec, inl = cv2.solvePnPRansac(
            xyz[use], nxt[use].astype(np.float64), rig.K, None, iterationsCount=200,
            reprojectionError=1.0, confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)
        assert found and inl is not None and len(inl) >= 30, "the reference lost track"
        prev_to_cur = np.eye(4)  # maps points of the previous camera into the current one
        prev_to_cur[:3, :3], prev_to_cur[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        poses.append(poses[-1] @ _inv(prev_to_cur))
        prev_l, prev_r = left, right
    return poses


def trapflow_vo(rig: StereoRig, frames: list[Path]) -> list[np.ndarray]:
    """trapflow's VO plugin, configured out of the box from the source's rig."""
    vo = StereoOdometry()
    vo.configure({}, make_context(rig, pool="vo"))
    poses = []
    for i, f in enumerate(frames):
        res = vo.process(make_pair(*vo_scene.load_pair(f), seq=i))
        assert res.ok, f"pair {i}: VO not ok"
        assert res.reinit == (i == 0), f"pair {i}: VO re-initialised"
        pose = np.eye(4)
        pose[:3, :4] = np.reshape(res.pose, (3, 4))
        poses.append(pose)
    return poses


@pytest.mark.parametrize("name", sorted(vo_scene.SEQUENCES))
def test_vo_drift_on_the_independent_scene(
    name: str, scene_frames: dict[str, tuple[list[np.ndarray], list[Path]]]
) -> None:
    truth, frames = scene_frames[name]
    truth = [_inv(truth[0]) @ t for t in truth]  # both estimates start at identity
    ours = drift(truth, trapflow_vo(vo_scene.RIG, frames))
    ref = drift(truth, reference_vo(vo_scene.RIG, frames))
    print(f"\n{name}: trapflow {ours[0]:.3f} % {ours[1]:.4f} deg/m; "
          f"reference {ref[0]:.3f} % {ref[1]:.4f} deg/m")
    assert ours[0] <= MAX_DRIFT_PCT and ours[1] <= MAX_DRIFT_DEG_PER_M, (ours, ref)
    assert ours[0] <= ref[0] and ours[1] <= ref[1], (ours, ref)
