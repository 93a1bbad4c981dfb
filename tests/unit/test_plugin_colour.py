"""Plugins say the colour they use: a grey plugin gets a JPEG pair decoded straight to grey."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import pytest
from trapflow_workers.apriltags import AprilTags
from trapflow_workers.crab_detector import CrabDetector
from trapflow_workers.stereo_vo import StereoOdometry

from tests import builders
from tests.builders import vo_circle, vo_plugin
from trapflow.errors import WorkerError
from trapflow.plugin import check_frame
from trapflow.pools.pair_path import decode_image
from trapflow.testing.kit import make_pair
from trapflow.testing.vo_metrics import as_4x4, drift_percent


def _jpeg(img: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()


def test_plugins_declare_their_colour() -> None:
    assert StereoOdometry.colour == AprilTags.colour == "grey"
    assert CrabDetector.colour == "bgr"


def test_grey_decoding_is_libjpegs_own_grey_and_raw_stays_bgr() -> None:
    img = builders.image(64, 48, seed=2)
    data = _jpeg(img)
    header = builders.pair_header(1, 64, 48, "jpeg")
    want = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    got = decode_image(data, header, "left", grey=True)
    assert got.shape == (48, 64) and int(np.abs(got.astype(int) - want).max()) <= 1
    raw = decode_image(img.tobytes(), builders.pair_header(1, 64, 48, "raw"), "left", grey=True)
    assert raw.shape == (48, 64, 3) and np.array_equal(raw, img)


def test_vo_on_grey_decoded_jpeg_matches_vo_on_bgr_decoded_jpeg() -> None:
    truth, frames = vo_circle()
    header = builders.pair_header(0, frames[0][0].shape[1], frames[0][0].shape[0], "jpeg")
    poses: dict[bool, list[np.ndarray]] = {}
    for grey in (False, True):
        vo = vo_plugin()
        out = []
        for i, (left, right) in enumerate(frames):
            lj, rj = _jpeg(left), _jpeg(right)
            pair = make_pair(decode_image(lj, header, "left", grey),
                             decode_image(rj, header, "right", grey), seq=i)
            out.append(vo.process(pair))
        assert all(r.ok for r in out)
        poses[grey] = [as_4x4(r.pose) for r in out]
    assert drift_percent(truth, poses[True], [0.5, 1.0, 1.5], step=2) < 1.5
    gap = max(float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
              for a, b in zip(poses[False], poses[True], strict=True))
    assert gap < 0.01, f"grey and BGR decoding gave poses {gap:.4f} m apart"


@pytest.mark.parametrize(("img", "grey_ok", "match"), [
    (np.zeros((48, 64), np.uint8), False, "expected a BGR uint8 left image"),
    (np.zeros((48, 64, 4), np.uint8), True, "expected a BGR uint8 left image"),
    (np.zeros((48, 64), np.float32), True, "expected a BGR uint8 left image"),
    (np.zeros((40, 64), np.uint8), True, "left image is 64x40, header says 64x48"),
])
def test_check_frame_rejects(img: Any, grey_ok: bool, match: str) -> None:
    with pytest.raises(WorkerError, match=match):
        check_frame(make_pair(img, header_size=(64, 48)), grey_ok=grey_ok)


def test_burn_spends_cpu_not_wall_time() -> None:
    """The VO floor bench's recogniser: it must cost CPU (a sleep would leave VO the cores)."""
    import time

    from trapflow.calibration.camera import StereoRig
    from trapflow.testing.kit import make_context
    from trapflow.testing.plugins import Burn

    burn = Burn()
    burn.configure({"cpu_s": 0.05}, make_context(StereoRig.from_fov(64, 48, 70.0, 0.12)))
    c = time.process_time()
    body = burn.process(make_pair(np.zeros((48, 64, 3), np.uint8)))
    assert time.process_time() - c >= 0.05 and body.fields["spins"] > 0
