"""VO's stereo depth on real pairs: OpenCV's stereo checkerboard set, rectified with the kit's
reference calibration.

The set is static board poses, not a sequence (and the board moves, not the rig), so VO's
motion cannot be checked on it. Its triangulation can: the points VO takes on the board must
lie on the board's plane as OpenCV's own chessboard detector and solvePnP place it, in the
set's units (squares), which also pins the baseline and the sign of the disparity.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from trapflow_workers.stereo_vo import StereoOdometry

from tests.conformance.conftest import kit_path
from trapflow.calibration.camera import StereoRig
from trapflow.testing.kit import make_context, make_pair

KIT = "01_stereo_checkerboard_opencv"
BOARD = (9, 6)  # inner corners
PAIRS = ["01", "02", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14"]


def _rectifier(root: Path) -> tuple[StereoRig, tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    ref = json.loads(kit_path(root, KIT, "reference_stereo_calib_ours.json").read_text())
    k1, d1, k2, d2, r, t = (np.array(ref[k], float) for k in ("K1", "D1", "K2", "D2", "R", "T"))
    size = (640, 480)
    r1, r2, p1, p2, _, _, _ = cv2.stereoRectify(k1, d1, k2, d2, size, r, t.reshape(3, 1),
                                                alpha=0)
    maps_l = cv2.initUndistortRectifyMap(k1, d1, r1, p1, size, cv2.CV_32FC1)
    maps_r = cv2.initUndistortRectifyMap(k2, d2, r2, p2, size, cv2.CV_32FC1)
    rig = StereoRig(width=size[0], height=size[1], fx=p1[0, 0], fy=p1[1, 1], cx=p1[0, 2],
                    cy=p1[1, 2], baseline_m=-p2[0, 3] / p2[0, 0])  # in squares, as the set
    return rig, maps_l, maps_r


def _board_points(root: Path) -> dict[str, np.ndarray | None]:
    """Per pair: the relative distances to the board plane of the VO points on the board
    (None when VO takes no keyframe)."""
    rig, maps_l, maps_r = _rectifier(root)
    assert rig.baseline_m == pytest.approx(3.336, abs=0.01)
    grid = np.zeros((BOARD[0] * BOARD[1], 3))
    grid[:, :2] = np.mgrid[0 : BOARD[0], 0 : BOARD[1]].T.reshape(-1, 2)
    out: dict[str, np.ndarray | None] = {}
    images = kit_path(root, KIT, "images")
    for name in PAIRS:
        left = cv2.remap(cv2.imread(str(images / f"left{name}.jpg")), *maps_l, cv2.INTER_LINEAR)
        right = cv2.remap(cv2.imread(str(images / f"right{name}.jpg")), *maps_r,
                          cv2.INTER_LINEAR)
        grey = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)
        found, corners = cv2.findChessboardCorners(grey, BOARD)
        assert found, f"OpenCV finds no board in rectified left{name}.jpg"
        corners = cv2.cornerSubPix(grey, corners, (11, 11), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        ok, rvec, tvec = cv2.solvePnP(grid, corners, rig.K, None)
        assert ok
        rot = cv2.Rodrigues(rvec)[0]
        normal, offset = rot[:, 2], float(rot[:, 2] @ tvec.ravel())  # plane: n . X = offset
        vo = StereoOdometry()
        vo.configure({}, make_context(rig, pool="vo"))
        res = vo.process(make_pair(left, right, seq=0))
        if not res.ok or vo.key is None:
            out[name] = None
            continue
        hull = cv2.convexHull(corners.reshape(-1, 2))
        inside = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), True) > 5
                           for x, y in vo.key.pts2d])
        on_board = vo.key.pts3d[inside]
        out[name] = np.abs(on_board @ normal - offset) / on_board[:, 2]
    return out


@pytest.mark.timeout(60)
def test_vo_takes_keyframes_whatever_the_calibration_units(realdata: Path) -> None:
    """Regression: the first keyframe's disparity guess assumed a point 2 m away, fx * B / 2,
    which is 835 px with this calibration in squares: VO took no keyframe in any pair. Now
    (a guess from the images) it takes one in most pairs, and on the board seen straight on
    (pair 01) 90 % of its board points are within 1 % of their depth from the board's plane."""
    points = _board_points(realdata)
    keyframes = [k for k, v in points.items() if v is not None]
    assert len(keyframes) >= 10, f"VO took a keyframe only in pairs {keyframes}"
    straight = points["01"]
    assert straight is not None and len(straight) >= 15
    print(f"\npair 01: {len(straight)} board points, 90th percentile distance to the plane "
          f"{np.percentile(straight, 90) * 100:.2f} % of depth; keyframes in {len(keyframes)} "
          f"of {len(PAIRS)} pairs")
    assert np.percentile(straight, 90) < 0.01


@pytest.mark.xfail(strict=True, reason="board disparities of 110-160 px on a periodic pattern: "
                   "the stereo match starts from one disparity guess for the whole image, and "
                   "a match one checker period off passes every check (pair 12)")
@pytest.mark.timeout(60)
def test_vo_board_points_are_on_the_board_in_every_pair(realdata: Path) -> None:
    """Known limitation, kept visible: in every pair VO takes 15+ board points, 90 % of them
    within 1 % of their depth from the board's plane."""
    points = _board_points(realdata)
    bad = {k: (None if v is None else (len(v), round(float(np.percentile(v, 90)), 4)))
           for k, v in points.items()
           if v is None or len(v) < 15 or np.percentile(v, 90) >= 0.01}
    assert not bad, f"pairs failing (None: no keyframe; else points, 90th pct): {bad}"
