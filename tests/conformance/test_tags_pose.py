"""Tag conformance: poses against the AprilTag C library's (pupil-apriltags) and a known pose.

Intrinsics and size as the C library's pose test assumes: fx = fy = 600, cx = w/2, cy = h/2,
tag 0.16 m. Independent check of the frame: the official tag image warped into a camera at a
known pose by a homography written here (an upright tag facing the camera must give identity).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from trapflow_workers.apriltags import C_PIXEL_CENTRE, c_library_detector, tag_object_points

from tests.conformance.conftest import PHOTOS, grey_render, kit_path, worker_for
from trapflow.testing.kit import make_pair

pytest.importorskip("pupil_apriltags", reason="pupil-apriltags is the reference")

SIZE = 0.16
FX = 600.0
MAX_DEG = 1.0
MAX_REL = 0.01


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle of the rotation between two rotation matrices."""
    return math.degrees(math.acos(float(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))))


def reprojection_px(r: np.ndarray, t: np.ndarray, k: np.ndarray, corners: np.ndarray) -> float:
    """RMS distance between corners and the tag's corners projected with pose (r, t)."""
    cam = (r @ tag_object_points(SIZE).T).T + t.ravel()
    uv = (k @ cam.T).T
    return float(np.sqrt(np.mean(np.sum((uv[:, :2] / uv[:, 2:] - corners) ** 2, axis=1))))


def ambiguity(corners: np.ndarray, k: np.ndarray) -> float:
    """Reprojection error of the worse of the two planar pose solutions over the better one:
    near 1 the corners cannot tell the two tilts apart (any estimator may pick either)."""
    _, rvecs, tvecs, _ = cv2.solvePnPGeneric(
        tag_object_points(SIZE), corners, k, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
    )
    errs = sorted(reprojection_px(cv2.Rodrigues(r)[0], t, k, corners)
                  for r, t in zip(rvecs, tvecs, strict=True))  # fmt: skip
    return errs[1] / max(errs[0], 1e-9)


@pytest.mark.parametrize("name", PHOTOS)
def test_pose_matches_the_c_library_on_its_photos(realdata: Path, name: str) -> None:
    """Where the pose is well determined (second solution reprojects 2x worse: 11 of the 46
    tags), rotation within 1 deg and translation within 1 % of the C library's (measured max
    0.97 deg, 0.32 %: the two minimise different errors on corners of 15-45 px tags). Elsewhere
    the C library's estimate may be the other tilt or (1 tag here) a reflection; there
    trapflow's pose must reproject at least as well as the C library's and be a rotation."""
    photo = kit_path(realdata, "02_apriltag36h11", "official_test_data", f"{name}.jpg")
    bgr = cv2.imread(str(photo))
    h, w = bgr.shape[:2]
    worker = worker_for(w, h, detector="apriltag", decimate=1.0)
    k = worker.rig.K
    ours = worker.process(make_pair(bgr)).tags
    ref = c_library_detector("tag36h11", decimate=1.0)
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    theirs = ref.detect(grey, estimate_tag_pose=True, camera_params=(FX, FX, w / 2, h / 2),
                        tag_size=SIZE)  # fmt: skip
    assert len(ours) == len(theirs) > 0
    compared = 0
    for d in theirs:
        corners = np.asarray(d.corners) - C_PIXEL_CENTRE  # onto trapflow's (OpenCV's) pixel grid
        tag = min(ours, key=lambda t: float(np.abs(np.asarray(t.corners) - corners).max()))
        assert np.abs(np.asarray(tag.corners) - corners).max() < 1e-3
        r, t = np.reshape(tag.rotation, (3, 3)), np.asarray(tag.translation)
        assert abs(np.linalg.det(r) - 1) < 1e-6
        proper = np.linalg.det(d.pose_R) > 0
        if proper and ambiguity(corners, k) >= 2.0:
            compared += 1
            assert angle_deg(r, d.pose_R) < MAX_DEG
            assert np.linalg.norm(t - d.pose_t.ravel()) < MAX_REL * np.linalg.norm(d.pose_t)
        else:
            ours_px = reprojection_px(r, t, k, corners)
            assert ours_px <= reprojection_px(d.pose_R, d.pose_t, k, corners) + 1e-3
    assert compared >= 3


def render_tag(png: Path, tag_to_cam: np.ndarray, k: np.ndarray, size: tuple[int, int]) -> tuple[
    np.ndarray, np.ndarray
]:
    """The official tag image seen by camera k at pose tag_to_cam (C library tag frame), by a
    homography from the tag plane, on a mid-grey background; and its corners p0..p3 in pixels."""
    scale = 12  # about the size the tag is seen at: warping shrinks or grows it little
    img = grey_render(png, scale, pad=0)  # 10 cells: the white border, then the black square
    cell = SIZE / 8
    # Tag plane (metres) from the scaled image's pixels, whose centres sit at integers: x_tag =
    # (x_png - 4.5) * cell with x_png = (x + 0.5) / scale - 0.5 in the 10-pixel official image.
    off = cell * (0.5 / scale - 5)
    plane = np.array([[cell / scale, 0, off], [0, cell / scale, off], [0, 0, 1]])
    rt = np.column_stack([tag_to_cam[:3, 0], tag_to_cam[:3, 1], tag_to_cam[:3, 3]])
    hmg = k @ rt @ plane
    out = cv2.warpPerspective(img, hmg, size, flags=cv2.INTER_LINEAR, borderValue=128)
    cam = (tag_to_cam[:3, :3] @ tag_object_points(SIZE).T).T + tag_to_cam[:3, 3]
    uv = (k @ cam.T).T
    return out, uv[:, :2] / uv[:, 2:]


def rot(axis: str, deg: float) -> np.ndarray:
    """Rotation matrix about a camera axis."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


@pytest.mark.parametrize(
    ("tag_id", "r", "t"),
    [
        (0, np.eye(3), (0.013, 0.021, 0.8)),  # upright, facing the camera: identity
        (42, np.eye(3), (0.2, -0.1, 1.5)),
        (7, rot("z", 30), (0.0, 0.1, 1.2)),
        (100, rot("x", 35) @ rot("z", -60), (-0.15, 0.05, 1.1)),
        (586, rot("y", -40) @ rot("z", 170), (0.1, 0.0, 0.9)),
    ],
    ids=["upright", "upright-off-centre", "roll-30", "tilt-35-roll-60", "yaw-40-roll-170"],
)
@pytest.mark.parametrize("detector", ["opencv", "apriltag"])
def test_pose_of_a_tag_rendered_at_a_known_pose(
    realdata: Path, tag_id: int, r: np.ndarray, t: tuple[float, float, float], detector: str
) -> None:
    """Regression for the 180 deg bug (issue 12): OpenCV's APRILTAG dictionaries hold each code
    turned 180 deg, so an upright tag facing the camera read as a half turn about the viewing
    axis with another first corner. Truth here is the pose the image was rendered at."""
    png = kit_path(realdata, "02_apriltag36h11", "tag_renders", f"tag36_11_{tag_id:05d}.png")
    w, h = 1280, 720
    worker = worker_for(w, h, detector=detector)
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = r, t
    grey, corners = render_tag(png, truth, worker.rig.K, (w, h))
    tags = worker.process(make_pair(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))).tags
    assert [tag.id for tag in tags] == [tag_id]
    tag = tags[0]
    # OpenCV's corners sit up to 1.5 px inside the square.
    np.testing.assert_allclose(tag.corners, corners, atol=0.5 if detector == "apriltag" else 2.0)
    assert angle_deg(np.reshape(tag.rotation, (3, 3)), r) < MAX_DEG
    assert np.linalg.norm(np.asarray(tag.translation) - t) < MAX_REL * np.linalg.norm(t)
    # The C library's own estimate puts the same frame on the same image.
    k = worker.rig.K  # the same camera on the C library's pixel grid: centres at +0.5
    cam = (k[0, 0], k[1, 1], k[0, 2] + C_PIXEL_CENTRE, k[1, 2] + C_PIXEL_CENTRE)
    (d,) = c_library_detector("tag36h11").detect(
        grey, estimate_tag_pose=True, camera_params=cam, tag_size=SIZE
    )
    assert angle_deg(d.pose_R, r) < MAX_DEG
