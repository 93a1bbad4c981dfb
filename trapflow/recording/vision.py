"""Detections as ROS 2 `vision_msgs/msg/Detection2DArray` in recordings, from definitions
found on this machine: no package on the index carries them and none are typed or copied
here. Where: a folder named in the config (`recording.vision_msgs`: the package's `msg/`
folder, the package folder, or a ROS prefix), else an installed ROS 2 environment (each
prefix of `AMENT_PREFIX_PATH`, its `share/vision_msgs/msg`). The .msg files are registered
with rosbags' get_types_from_msg and flattened as rosbag2 writes schemas into MCAP. Pure
but for reading those files; the recorder writes what detection_array() builds.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from trapflow.recording.msgs import header

DETECTION_ARRAY = "vision_msgs/msg/Detection2DArray"
# Detection2DArray and every vision_msgs type it holds (the rest come from ROS 2 humble).
_TYPES = ("Point2D", "Pose2D", "BoundingBox2D", "ObjectHypothesis", "ObjectHypothesisWithPose",
          "Detection2D", "Detection2DArray")
# How the definitions were looked for, for the one line that says none were found.
WHERE = "recording.vision_msgs in the config, or share/vision_msgs/msg of AMENT_PREFIX_PATH"


@dataclass(frozen=True)
class Definitions:
    """The flattened Detection2DArray definition and the folder it was read from."""

    msgdef: str
    folder: Path


def _candidates(configured: str, env: Mapping[str, str]) -> list[Path]:
    out: list[Path] = []
    if configured:
        base = Path(configured).expanduser()
        out += [base, base / "msg", base / "share" / "vision_msgs" / "msg"]
    for prefix in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            out.append(Path(prefix) / "share" / "vision_msgs" / "msg")
    return out


def find(configured: str = "", env: Mapping[str, str] | None = None) -> Definitions | None:
    """The definitions of Detection2DArray from the first folder that has all of them, or
    None. A folder whose definitions do not parse, or are not the vision_msgs 4 layout
    this writes (Pose2D with a position), raises ValueError saying which and why."""
    for folder in _candidates(configured, os.environ if env is None else env):
        if all((folder / f"{name}.msg").is_file() for name in _TYPES):
            return Definitions(_flatten(folder), folder)
    return None


def _flatten(folder: Path) -> str:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)  # a fresh store: nothing registered globally
    types: dict[str, Any] = {}
    for name in _TYPES:
        path = folder / f"{name}.msg"
        try:
            types.update(get_types_from_msg(path.read_text(encoding="utf-8"),
                                            f"vision_msgs/msg/{name}"))
        except Exception as exc:  # noqa: BLE001 - rosbags' parser raises its own types
            raise ValueError(f"{path}: not a ROS 2 message definition: {exc}") from None
    store.register(types)
    pose = [f[0] for f in types["vision_msgs/msg/Pose2D"][1]]
    if "position" not in pose:
        raise ValueError(f"{folder}: expected vision_msgs 4 (Pose2D with a position), got "
                         f"Pose2D fields {pose}; point recording.vision_msgs at vision_msgs 4")
    text, _ = store.generate_msgdef(DETECTION_ARRAY, ros_version=2)
    return str(text)


def detection_array(items: Sequence[dict[str, Any]], t_ns: int, frame_id: str
                    ) -> dict[str, Any]:
    """vision_msgs/Detection2DArray of one pair's mono_ir result items: a box [x1, y1, x2,
    y2] in pixels becomes its centre and size, the label and confidence one hypothesis (its
    pose unknown: zero, zero covariance), the track id the detection's id ("" unconfirmed).
    A pair where nothing was detected gives an empty array: seen nothing, not missing."""
    hdr = header(t_ns, frame_id)
    detections = []
    for it in items:
        box = it.get("box") or []
        if len(box) != 4:
            continue
        x1, y1, x2, y2 = (float(v) for v in box)
        track = it.get("track")
        detections.append({
            "header": hdr,
            "results": [{
                "hypothesis": {"class_id": str(it.get("label", "")),
                               "score": float(it.get("confidence", 0.0))},
                "pose": {"pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                                  "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                         "covariance": [0.0] * 36}}],
            "bbox": {"center": {"position": {"x": (x1 + x2) / 2, "y": (y1 + y2) / 2},
                                "theta": 0.0},
                     "size_x": x2 - x1, "size_y": y2 - y1},
            "id": "" if track is None else str(track)})
    return {"header": hdr, "detections": detections}
