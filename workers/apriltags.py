"""tags: AprilTag detection (OpenCV's detector) with pose from the tag size and the intrinsics.

Pose: tag frame x right, y up, z out of the tag towards the viewer, origin at the tag
centre; rotation and translation map tag coordinates into the OpenCV camera frame
(solvePnP, square-tag IPPE). Corners: top-left, top-right, bottom-right, bottom-left.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Annotated, Any, Literal

import cv2
import msgspec
import numpy as np
from trapflow_workers.calibration import resolve_rig
from trapflow_workers.common import Params, check_frame, floats, parse_params

from trapflow.messages import Tag, Tags
from trapflow.plugin import Context, Pair, Worker

log = logging.getLogger(__name__)

FAMILIES = {
    "36h11": cv2.aruco.DICT_APRILTAG_36h11,
    "36h10": cv2.aruco.DICT_APRILTAG_36h10,
    "25h9": cv2.aruco.DICT_APRILTAG_25h9,
    "16h5": cv2.aruco.DICT_APRILTAG_16h5,
}
Pos = Annotated[float, msgspec.Meta(gt=0)]


class TagParams(Params):
    """`pools.tags.params`: every key is optional."""

    family: Literal["36h11", "36h10", "25h9", "16h5"] = "36h11"
    """AprilTag family."""
    tag_size_m: Pos = 0.1
    """Edge of the black square, in metres."""
    sizes: dict[int, Pos] = {}
    """Per-id tag sizes overriding tag_size_m."""
    calibration: str = ""
    """KITTI calib.txt or YAML (fx, fy, cx, cy, baseline_m[, width, height]); overrides the rig."""
    intrinsics: tuple[Pos, Pos, Pos, Pos] | None = None
    """fx, fy, cx, cy in pixels, instead of the source's rig."""
    image: Literal["left", "right"] = "left"
    """Which image of the pair to search (both share the intrinsics once rectified)."""
    refine: Literal["subpix", "apriltag", "none"] = "subpix"
    """Corner refinement: subpix is fast but puts corners ~0.4 px inside the square (tags
    read ~1 % too far at 1280x720, up to 3 % at 640x480 for 12 cm tags at 1.3 m); apriltag
    fits the edges (~0.1 %) at 7-8x the cost; none is 2x worse than subpix."""


class AprilTags(Worker):
    """Detect tags, solve each tag's pose, report the reprojection error in pixels."""

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        p = parse_params(params, TagParams, ctx.pool)
        self.p = p
        self.rig = resolve_rig(p.calibration, p.intrinsics, None, ctx.rig)
        det = cv2.aruco.DetectorParameters()
        det.cornerRefinementMethod = {
            "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
            "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
            "none": cv2.aruco.CORNER_REFINE_NONE,
        }[p.refine]
        dictionary = cv2.aruco.getPredefinedDictionary(FAMILIES[p.family])
        self.detector = cv2.aruco.ArucoDetector(dictionary, det)
        log.info("tags: family %s, size %.3f m, fx=%.1f", p.family, p.tag_size_m, self.rig.fx)

    def _object(self, tag_id: int) -> np.ndarray:
        h = self.p.sizes.get(tag_id, self.p.tag_size_m) / 2.0
        return np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], np.float64)

    def process(self, pair: Pair) -> Tags:
        check_frame(pair, (self.rig.width, self.rig.height), "the calibration's image size")
        image = pair.left if self.p.image == "left" else pair.right
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _ = self.detector.detectMarkers(gray)
        if ids is None:
            return Tags(tags=[])
        K = self.rig.K  # noqa: N806 - the usual name of the matrix
        tags = []
        for quad, tag_id in zip(corners, ids.ravel(), strict=True):
            px = quad.reshape(4, 2).astype(np.float64)
            obj = self._object(int(tag_id))
            ok, rvec, tvec = cv2.solvePnP(obj, px, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            if not ok:
                continue
            proj, _ = cv2.projectPoints(obj, rvec, tvec, K, None)
            err = float(np.sqrt(np.mean(np.sum((proj.reshape(4, 2) - px) ** 2, axis=1))))
            t = tvec.ravel()
            tags.append(
                Tag(
                    id=int(tag_id),
                    corners=[(float(x), float(y)) for x, y in px],
                    rotation=floats(cv2.Rodrigues(rvec)[0]),
                    translation=(float(t[0]), float(t[1]), float(t[2])),
                    error=err,
                )
            )
        return Tags(tags=sorted(tags, key=lambda tag: tag.id))
