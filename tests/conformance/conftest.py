"""Conformance harness: third-party data from the real-data kit, read in place, never copied.

The kit lives beside the project (`../shared/realdata` from the project root) or wherever
TRAPFLOW_REALDATA points. Each test that needs it skips with the reason when it is absent
(a user's fresh clone has no kit).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from trapflow.calibration.camera import StereoRig
from trapflow.testing.kit import make_context

REPO = Path(__file__).resolve().parents[2]


def realdata_root() -> Path:
    """Where the real-data kit is expected: $TRAPFLOW_REALDATA, else ../shared/realdata."""
    env = os.environ.get("TRAPFLOW_REALDATA")
    return Path(env) if env else REPO.parent / "shared" / "realdata"


@pytest.fixture
def realdata() -> Path:
    """The kit's root; skips the test with a clear reason when it is not there."""
    root = realdata_root()
    if not (root / "MANIFEST.md").is_file():
        pytest.skip(f"real-data kit not found at {root} (set TRAPFLOW_REALDATA to its folder)")
    return root


def kit_path(root: Path, *parts: str) -> Path:
    """A file or folder of the kit; skips when that part of the kit is missing."""
    p = root.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real-data kit has no {Path(*parts)}")
    return p


# --- AprilTag references, shared by the detection and the pose tests -----------------------

# The AprilTag C library's test photos (02_apriltag36h11/photos) with expected corners.
PHOTOS = ["33369213973_9d9bb4cc96_c", "34085369442_304b6bafd9_c", "34139872896_defdb2f8d9_c"]


def worker_for(width: int, height: int, **params: Any) -> Any:
    """The tags worker on a rig of this image size with the C library's pose-test intrinsics
    (fx = fy = 600, cx = w/2, cy = h/2 on its pixel grid, whose pixel centres sit at +0.5:
    trapflow's grid, OpenCV's, has them at 0, so the same camera has cx = w/2 - 0.5 there)."""
    from trapflow_workers.apriltags import C_PIXEL_CENTRE, AprilTags

    rig = StereoRig(width=width, height=height, fx=600.0, fy=600.0, cx=width / 2 - C_PIXEL_CENTRE,
                    cy=height / 2 - C_PIXEL_CENTRE, baseline_m=0.1)  # fmt: skip
    w = AprilTags()
    w.configure({"tag_size_m": 0.16, **params}, make_context(rig, pool="tags"))
    return w


def grey_render(path: Path, scale: int, pad: int = 40) -> np.ndarray:
    """An official tag image (RGBA, transparent = white) scaled up by nearest neighbour."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, f"cannot read {path}"
    grey = img[..., :3].mean(axis=2) if img.ndim == 3 else img.astype(float)
    if img.ndim == 3 and img.shape[2] == 4:
        grey = np.where(img[..., 3] == 0, 255, grey)
    big = cv2.resize(grey.astype(np.uint8), None, fx=scale, fy=scale,
                     interpolation=cv2.INTER_NEAREST)  # fmt: skip
    return cv2.copyMakeBorder(big, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
