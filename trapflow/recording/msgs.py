"""Message definitions and pure converters for recordings: what ROS tools and Foxglove read.

Definitions are never hand-written: ROS types come from the rosbags typestore (ROS 2 humble),
flattened the way rosbag2 stores them in MCAP schemas; Foxglove's ImageAnnotations is
translated field by field from the protobuf descriptor that foxglove-schemas-protobuf ships
into a ROS 2 definition named foxglove_msgs/msg/..., which Foxglove draws on images and ROS
readers decode (an MCAP with the ros2 profile holds ROS 2 messages only: a protobuf
channel there makes rosbags refuse the whole file). The converters turn a stereo rig,
normalized result lines and VO poses into message dicts; they touch no file or socket.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import cache
from typing import Any

from trapflow.calibration.camera import StereoRig

FRAME_ODOM = "trapflow_odom"
SEP = "=" * 80 + "\n"

# Colours per result kind, RGBA in 0..1.
_BOX_RGBA = {"mono_ir": (1.0, 0.35, 0.1, 1.0), "tags": (0.1, 0.9, 0.3, 1.0)}


@cache
def ros_msgdef(typename: str) -> str:
    """The flattened ROS 2 definition of typename (e.g. 'nav_msgs/msg/Odometry')."""
    from rosbags.typesys import Stores, get_typestore

    text, _ = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(typename, ros_version=2)
    return str(text)


# protobuf FieldDescriptor.type numbers -> ROS 2 primitive types
_PROTO_PRIMITIVES = {1: "float64", 2: "float32", 3: "int64", 4: "uint64", 5: "int32",
                     8: "bool", 9: "string", 12: "uint8[]", 13: "uint32", 17: "int32",
                     18: "int64"}
_TYPE_MESSAGE, _TYPE_ENUM = 11, 14
_SKIPPED_FIELDS = {"metadata"}  # key/value lists the ROS 2 foxglove_msgs do not carry


def _ros_name(proto_full_name: str) -> str:
    if proto_full_name == "google.protobuf.Timestamp":
        return "builtin_interfaces/Time"
    package, _, name = proto_full_name.rpartition(".")
    if package != "foxglove":
        raise ValueError(f"no ROS 2 counterpart for protobuf message {proto_full_name}")
    return f"foxglove_msgs/{name}"


def _proto_fields(desc: Any) -> tuple[str, list[Any]]:
    """One message's ROS 2 definition text and the protobuf messages it refers to."""
    lines: list[str] = []
    refs: list[Any] = []
    for f in desc.fields:
        if f.name in _SKIPPED_FIELDS:
            continue
        if f.type == _TYPE_MESSAGE:
            ros_type = _ros_name(f.message_type.full_name)
            refs.append(f.message_type)
        elif f.type == _TYPE_ENUM:
            ros_type = "uint8"
            lines += [f"uint8 {v.name}={v.number}" for v in f.enum_type.values]
        else:
            ros_type = _PROTO_PRIMITIVES[f.type]
        suffix = "[]" if f.is_repeated and not ros_type.endswith("[]") else ""
        lines.append(f"{ros_type}{suffix} {f.name}")
    return "".join(line + "\n" for line in lines), refs


@cache
def foxglove_msgdef(name: str = "ImageAnnotations") -> tuple[str, str]:
    """(ROS 2 type name, flattened definition) of a Foxglove schema, from its protobuf
    descriptor in foxglove-schemas-protobuf. ImportError when the package is not installed."""
    import importlib

    module = importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2")
    root = getattr(module, name).DESCRIPTOR
    text, refs = _proto_fields(root)
    seen = {root.full_name}
    while refs:
        desc = refs.pop(0)
        if desc.full_name in seen:
            continue
        seen.add(desc.full_name)
        if desc.full_name == "google.protobuf.Timestamp":
            body = ros_msgdef("builtin_interfaces/msg/Time").split(SEP)[0]
        else:
            body, more = _proto_fields(desc)
            refs += more
        text += SEP + f"MSG: {_ros_name(desc.full_name)}\n" + body
    return f"foxglove_msgs/msg/{name}", text


def stamp(t_ns: int) -> dict[str, int]:
    """builtin_interfaces/Time of a wall-clock time in ns."""
    return {"sec": t_ns // 1_000_000_000, "nanosec": t_ns % 1_000_000_000}


def header(t_ns: int, frame_id: str) -> dict[str, Any]:
    """std_msgs/Header."""
    return {"stamp": stamp(t_ns), "frame_id": frame_id}


def tf_static(rig: StereoRig, t_ns: int, left: str, right: str) -> dict[str, Any]:
    """tf2_msgs/TFMessage: the right camera in the left camera's frame. The rig is
    rectified, so the right camera sits baseline metres along the left camera's x axis."""
    return {"transforms": [{
        "header": header(t_ns, left), "child_frame_id": right,
        "transform": {"translation": {"x": float(rig.baseline_m), "y": 0.0, "z": 0.0},
                      "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}]}


def quaternion(r: Sequence[Sequence[float]]) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a 3x3 rotation matrix (Shepperd's method, w >= 0)."""
    m00, m01, m02 = r[0][0], r[0][1], r[0][2]
    m10, m11, m12 = r[1][0], r[1][1], r[1][2]
    m20, m21, m22 = r[2][0], r[2][1], r[2][2]
    tr = m00 + m11 + m22
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = ((m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s)
    elif m00 > m11 and m00 > m22:
        s = math.sqrt(1.0 + m00 - m11 - m22) * 2
        q = (0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s)
    elif m11 > m22:
        s = math.sqrt(1.0 + m11 - m00 - m22) * 2
        q = ((m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s)
    else:
        s = math.sqrt(1.0 + m22 - m00 - m11) * 2
        q = ((m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s)
    n = math.sqrt(sum(v * v for v in q))
    x, y, z, w = (v / n for v in q)
    return (-x, -y, -z, -w) if w < 0 else (x, y, z, w)


def pose_of(pose_rows: Sequence[Sequence[float]]) -> dict[str, Any]:
    """geometry_msgs/Pose of a 3x4 [R | t] pose (the left camera in the VO's start frame)."""
    x, y, z, w = quaternion([row[:3] for row in pose_rows])
    return {"position": {"x": float(pose_rows[0][3]), "y": float(pose_rows[1][3]),
                         "z": float(pose_rows[2][3])},
            "orientation": {"x": x, "y": y, "z": z, "w": w}}


def odometry(pose_rows: Sequence[Sequence[float]], t_ns: int, child: str) -> dict[str, Any]:
    """nav_msgs/Odometry of a VO pose; the covariances are unknown (all zero) and so is the
    twist."""
    zero3 = {"x": 0.0, "y": 0.0, "z": 0.0}
    return {"header": header(t_ns, FRAME_ODOM), "child_frame_id": child,
            "pose": {"pose": pose_of(pose_rows), "covariance": [0.0] * 36},
            "twist": {"twist": {"linear": zero3, "angular": dict(zero3)},
                      "covariance": [0.0] * 36}}


def path(poses: Sequence[tuple[int, Sequence[Sequence[float]]]]) -> dict[str, Any]:
    """nav_msgs/Path of (time, 3x4 pose) pairs, stamped with the last pose's time."""
    t_last = poses[-1][0] if poses else 0
    return {"header": header(t_last, FRAME_ODOM),
            "poses": [{"header": header(t, FRAME_ODOM), "pose": pose_of(p)} for t, p in poses]}


def _color(rgba: tuple[float, float, float, float]) -> dict[str, float]:
    return dict(zip("rgba", rgba, strict=True))


def _point(x: float, y: float) -> dict[str, float]:
    return {"x": float(x), "y": float(y)}


def image_annotations(algo: str, items: Sequence[dict[str, Any]], t_ns: int) -> dict[str, Any]:
    """foxglove_msgs/msg/ImageAnnotations of one pair's normalized result items of algo:
    mono_ir boxes [x1, y1, x2, y2] as closed outlines with `label confidence`, tags as their
    four corners with the tag id. Items without geometry (label none, no tag) draw nothing."""
    rgba = _BOX_RGBA.get(algo, (1.0, 1.0, 0.0, 1.0))
    ts = stamp(t_ns)
    clear = _color((0.0, 0.0, 0.0, 0.0))
    points: list[dict[str, Any]] = []
    texts: list[dict[str, Any]] = []
    for it in items:
        if algo == "mono_ir" and len(it.get("box") or []) == 4:
            x1, y1, x2, y2 = it["box"]
            corners = [(x1, y1), (x2, y1), (x2, y2), (x1, y2)]
            label = f"{it.get('label', '')} {float(it.get('confidence', 0.0)):.2f}"
        elif algo == "tags" and len(it.get("corners") or []) == 4:
            corners = [tuple(c) for c in it["corners"]]
            x1 = min(c[0] for c in corners)
            y1 = min(c[1] for c in corners)
            label = f"tag {it.get('id', '?')}"
        else:
            continue
        points.append({"timestamp": ts, "type": 2, "points": [_point(x, y) for x, y in corners],
                       "outline_color": _color(rgba), "outline_colors": [], "fill_color": clear,
                       "thickness": 2.0})
        texts.append({"timestamp": ts, "position": _point(x1, max(y1 - 4.0, 0.0)),
                      "text": label, "font_size": 12.0, "text_color": _color(rgba),
                      "background_color": _color((0.0, 0.0, 0.0, 0.6))})
    return {"timestamp": ts, "circles": [], "points": points, "texts": texts}
