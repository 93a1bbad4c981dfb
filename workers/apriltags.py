"""tags: AprilTag detection with pose, corners and tag frame as the AprilTag C library has them.

Detector: the AprilTag C library itself (through pupil-apriltags, the optional `tags` extra) when
it is installed, else OpenCV's ArUco APRILTAG dictionaries with their corners put in the C
library's order. On the C library's own test photos the library finds 46 of 47 tags with corners
within 0.14 px of its expectations; OpenCV places 35 of them, 1.2 px inside the square (median).
At 1280x720, one thread, the library took 70-78 ms (25-46 at decimate 2), OpenCV 57-103 ms
(medians of 30 runs over 3 sessions on a busy 2-core machine: the same cost within its noise).

Corners, in the order of the C library's `det->p` (counter-clockwise in the image): p0 bottom-left,
p1 bottom-right, p2 top-right, p3 top-left of the tag as printed upright (as the official tag
images are drawn). OpenCV's dictionaries store each code turned 180 degrees, so its first corner is
the C library's p1 and its order runs the other way: C order = OpenCV corners [1, 0, 3, 2].
Positions are in OpenCV's pixel convention (a pixel's centre at integer coordinates), the one of
the rig's intrinsics and of every other trapflow result: the C library's own numbers are 0.5 px
larger in x and y (its pixel centres sit at +0.5).

Tag frame (apriltag_pose.h): origin at the tag centre, x to the right and y down of the tag as
printed upright, z into the tag; p0..p3 sit at (-s/2, s/2), (s/2, s/2), (s/2, -s/2), (-s/2, -s/2).
`rotation` (3x3, row major) and `translation` (metres) map tag coordinates into the camera frame
(x right, y down, z forward): an upright tag facing the camera has rotation ~identity.

Pose: IPPE on the four corners (OpenCV's SOLVEPNP_IPPE_SQUARE, whose corner order is p0..p3),
both solutions refined to the least reprojection error, the lower one kept. On the C library's
test photos it agrees with the library's own estimate (orthogonal iteration, object-space error)
on the 11 tags whose pose the corners determine (median 0.01 deg, max 0.97 deg, 0.32 %); where a
tag's two tilts reproject alike the two pick either, and the library's was a reflection (det -1)
for 1 of the 46 tags.
"""

from __future__ import annotations

import atexit
import functools
import logging
import math
from collections.abc import Mapping
from typing import Annotated, Any, Literal

import cv2
import msgspec
import numpy as np

from trapflow.plugin import (
    ConfigError,
    Context,
    Pair,
    Params,
    Tag,
    Tags,
    Worker,
    WorkerError,
    check_frame,
    parse_params,
)

from .calibration import resolve_rig
from .common import floats, to_grey

log = logging.getLogger(__name__)

FAMILIES = {
    "36h11": cv2.aruco.DICT_APRILTAG_36h11,
    "36h10": cv2.aruco.DICT_APRILTAG_36h10,
    "25h9": cv2.aruco.DICT_APRILTAG_25h9,
    "16h5": cv2.aruco.DICT_APRILTAG_16h5,
}
# Families given to the C library (36h10 is not in it any more).
C_FAMILIES = {"36h11": "tag36h11", "25h9": "tag25h9", "16h5": "tag16h5"}
OPENCV_TO_C = [1, 0, 3, 2]
# The C library's pixel grid puts a pixel's centre at +0.5, OpenCV's (and so the rig's K) at 0:
# on tags warped at 30 random poses its corners sat +0.50 px (sd 0.02) from the truth with edge
# refinement, +0.43 (sd 0.04) from its quad fit alone.
C_PIXEL_CENTRE = 0.5
Pos = Annotated[float, msgspec.Meta(gt=0)]
# Where neither the params nor the source say how big the tags are (a camera, no config).
FALLBACK_TAG_SIZE_M = 0.1


class TagParams(Params):
    """`pools.tags.params`: every key is optional."""

    family: Literal["36h11", "36h10", "25h9", "16h5"] = "36h11"
    """AprilTag family."""
    tag_size_m: Pos | None = None
    """Edge of the black square, in metres. Unset: the size the source lays (a synthetic
    world publishes its own), else 0.1. A size that contradicts the source's is an error."""
    sizes: dict[int, Pos] = {}
    """Per-id tag sizes overriding tag_size_m."""
    calibration: str = ""
    """KITTI calib.txt or YAML (fx, fy, cx, cy, baseline_m[, width, height]); overrides the rig."""
    intrinsics: tuple[Pos, Pos, Pos, Pos] | None = None
    """fx, fy, cx, cy in pixels, instead of the source's rig."""
    image: Literal["left", "right"] = "left"
    """Which image of the pair to search (both share the intrinsics once rectified)."""
    detector: Literal["auto", "apriltag", "opencv"] = "auto"
    """apriltag: the AprilTag C library (`pip install trapflow[tags]`; all families but 36h10);
    opencv: OpenCV's ArUco dictionaries (corners 1.2 px inside the square, fewer small tags);
    auto: the C library when it is installed and has the family, else OpenCV."""
    refine: bool = True
    """OpenCV: refine the corners with cornerSubPix (without, poses are ~2x worse)."""
    decimate: Annotated[float, msgspec.Meta(ge=1, le=8)] = 1.0
    """C library: find quads on an image this many times smaller, then snap their edges back
    to full-size gradients (refine_edges). 2 is ~3x faster at 1280x720 but found 29 of the 47
    tags of the library's test photos (46 at 1). At 1 the quads are fitted at full size and
    refine_edges stays off: on those photos it lost 2 tags, and it did not improve poses on
    the synthetic world (median 0.05 deg without, 0.11 with, at 1280x720)."""
    threads: Annotated[int, msgspec.Meta(ge=1, le=8)] = 1
    """C library: threads of one detection (the pool's processes already share the cores)."""


@functools.lru_cache(maxsize=8)
def c_library_detector(family: str, decimate: float = 1.0, threads: int = 1) -> Any:
    """A pupil-apriltags Detector (edge refinement only when decimating, see TagParams), one
    per process and settings, never freed.

    pupil-apriltags 1.0.4 frees the tag families before the detector that still reads them
    (use after free): a freed detector that had run crashed the process in 6 of 7 runs.
    """
    from pupil_apriltags import Detector

    det = Detector(
        families=family, nthreads=threads, quad_decimate=decimate, refine_edges=int(decimate > 1)
    )
    atexit.register(_leak, det)
    return det


def _leak(det: Any) -> None:
    det.tag_detector_ptr = None  # its __del__ then frees nothing


def _c_library_available() -> bool:
    try:
        import pupil_apriltags  # noqa: F401
    except ImportError:
        return False
    return True


def tag_size(p: TagParams, ctx: Context) -> float:
    """The run's one tag size: the params', else the source's, else FALLBACK_TAG_SIZE_M.

    ConfigError when a configured size (or a per-id one) contradicts the size the source
    lays: every pose would be off by their ratio (0.10 m assumed of 0.12 m tags put every
    tag 16.5 % too near).
    """
    src = ctx.tag_size_m
    if src is not None:
        given = [("tag_size_m", p.tag_size_m)] + [(f"sizes.{i}", v) for i, v in p.sizes.items()]
        for key, size in given:
            if size is not None and not math.isclose(size, src, rel_tol=1e-6):
                raise ConfigError(
                    f"pools.{ctx.pool}.params.{key}: expected the source's tag size "
                    f"{src:g} m (the tags it lays), got {size:g} m; remove the key to take "
                    f"the source's, or have the source lay {size:g} m tags "
                    f"(source.options.tag_size_m)")
        return src
    if p.tag_size_m is not None:
        return p.tag_size_m
    log.warning("tags: the source does not say how big its tags are and "
                "pools.%s.params.tag_size_m is unset: assuming %g m (every range scales "
                "with it)", ctx.pool, FALLBACK_TAG_SIZE_M)
    return FALLBACK_TAG_SIZE_M


def tag_object_points(size_m: float) -> np.ndarray:
    """The four corners p0..p3 in the tag frame (x right, y down, z into the tag), metres."""
    h = size_m / 2.0
    return np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], np.float64)


def _rms(obj: np.ndarray, rvec: Any, tvec: Any, k: np.ndarray, px: np.ndarray) -> float:
    """Root mean square distance, in pixels, between the corners and their reprojection."""
    proj, _ = cv2.projectPoints(obj, rvec, tvec, k, None)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(4, 2) - px) ** 2, axis=1))))


class AprilTags(Worker):
    """Detect tags, solve each tag's pose, report the reprojection error in pixels."""

    colour = "grey"  # a JPEG pair is decoded straight to grey

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        p = parse_params(params, TagParams, ctx.pool)
        self.p = p
        self.size = tag_size(p, ctx)
        self.rig = resolve_rig(p.calibration, p.intrinsics, None, ctx.rig)
        self.backend = self._backend(p, ctx.pool)
        if self.backend == "apriltag":
            self.c_detector = c_library_detector(C_FAMILIES[p.family], p.decimate, p.threads)
        else:
            det = cv2.aruco.DetectorParameters()
            det.cornerRefinementMethod = (
                cv2.aruco.CORNER_REFINE_SUBPIX if p.refine else cv2.aruco.CORNER_REFINE_NONE
            )
            dictionary = cv2.aruco.getPredefinedDictionary(FAMILIES[p.family])
            self.detector = cv2.aruco.ArucoDetector(dictionary, det)
        log.info(
            "tags: %s detector, family %s, size %.3f m, fx=%.1f",
            self.backend, p.family, self.size, self.rig.fx,
        )

    @staticmethod
    def _backend(p: TagParams, pool: str) -> str:
        if p.detector == "opencv":
            return "opencv"
        where = f"pools.{pool}.params.detector"
        if p.family not in C_FAMILIES:
            if p.detector == "auto":
                return "opencv"
            raise WorkerError(
                f"{where}: expected a family the C library detector handles "
                f"({', '.join(C_FAMILIES)}), got {p.family!r}; set detector: opencv"
            )
        if _c_library_available():
            return "apriltag"
        if p.detector == "apriltag":
            raise WorkerError(
                f"{where}: the AprilTag C library (pupil-apriltags) is not installed; "
                "install it with `pip install trapflow[tags]`, or set detector: opencv"
            )
        log.warning(
            "tags: pupil-apriltags is not installed, so OpenCV's detector runs (corners 1.2 px "
            "inside the square, fewer small tags); `pip install trapflow[tags]` for the C library"
        )
        return "opencv"

    def detect(self, gray: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """(id, corners p0..p3 as a 4x2 float64 array) of every tag in a grey image."""
        if self.backend == "apriltag":
            dets = self.c_detector.detect(np.ascontiguousarray(gray))
            return [
                (int(d.tag_id), np.asarray(d.corners, np.float64) - C_PIXEL_CENTRE) for d in dets
            ]
        corners, ids, _ = self.detector.detectMarkers(gray)
        if ids is None:
            return []
        return [
            (int(i), q.reshape(4, 2)[OPENCV_TO_C].astype(np.float64))
            for q, i in zip(corners, ids.ravel(), strict=True)
        ]

    def process(self, pair: Pair) -> Tags:
        rig = self.rig
        if rig is None:
            raise WorkerError("tags: expected configure() before process(), got no rig")
        check_frame(pair, (rig.width, rig.height), "the calibration's image size",
                    grey_ok=True)
        image = pair.left if self.p.image == "left" else pair.right
        gray = to_grey(image)
        K = rig.K  # noqa: N806 - the usual name of the matrix
        tags = []
        for tag_id, px in self.detect(gray):
            obj = tag_object_points(self.p.sizes.get(tag_id, self.size))
            n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
                obj, px, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
            )
            if n == 0:
                continue
            # IPPE solves from the homography; a few Levenberg-Marquardt steps then minimise
            # the reprojection error itself (IPPE alone was up to 4 % above the minimum).
            for r, t in zip(rvecs, tvecs, strict=True):
                cv2.solvePnPRefineLM(obj, px, K, None, r, t)
            errs = [_rms(obj, r, t, K, px) for r, t in zip(rvecs, tvecs, strict=True)]
            best = int(np.argmin(errs))
            rvec, t = rvecs[best], tvecs[best].ravel()
            tags.append(
                Tag(
                    id=tag_id,
                    corners=[(float(x), float(y)) for x, y in px],
                    rotation=floats(cv2.Rodrigues(rvec)[0]),
                    translation=(float(t[0]), float(t[1]), float(t[2])),
                    error=errs[best],
                )
            )
        return Tags(tags=sorted(tags, key=lambda tag: tag.id))
