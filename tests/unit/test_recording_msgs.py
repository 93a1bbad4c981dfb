"""Recording message definitions and converters, checked against independent references:
rosbags' own .msg parser and serializer, foxglove's protobuf descriptors, OpenCV's Rodrigues."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from mcap_ros2.writer import Writer
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from trapflow.recording import msgs


def typestore_with_annotations() -> Any:
    name, text = msgs.foxglove_msgdef()
    store = get_typestore(Stores.ROS2_HUMBLE)
    # rosbags parses the flattened definition the way it reads one from a bag.
    parts = text.split(msgs.SEP)
    types = get_types_from_msg(parts[0], name)
    for part in parts[1:]:
        head, _, body = part.partition("\n")
        sub = head.removeprefix("MSG: ").replace("/", "/msg/", 1)
        types.update(get_types_from_msg(body, sub))
    store.register(types)
    return store


def test_annotations_definition_mirrors_the_foxglove_descriptor() -> None:
    store = typestore_with_annotations()
    fields = {f[0] for f in store.fielddefs["foxglove_msgs/msg/ImageAnnotations"][1]}
    proto = {f.name for f in ImageAnnotations.DESCRIPTOR.fields} - {"metadata"}
    assert fields == proto
    points = store.fielddefs["foxglove_msgs/msg/PointsAnnotation"]
    consts = {c[0]: c[2] for c in points[0]}
    assert consts == {"UNKNOWN": 0, "POINTS": 1, "LINE_LOOP": 2, "LINE_STRIP": 3, "LINE_LIST": 4}


def test_annotations_of_boxes_and_tags_decode_in_rosbags(tmp_path: Path) -> None:
    """Written with mcap's ROS 2 writer, read with rosbags: the definition is what the bag
    says the data is."""
    items = [{"label": "crab", "confidence": 0.71, "box": [5.4, 7.8, 15.6, 18.1]},
             {"label": "none", "confidence": 0.0, "box": []}]
    msg = msgs.image_annotations("mono_ir", items, 1_751_892_763_120_000_000)
    tags = msgs.image_annotations("tags", [{"id": 7, "corners": [[1, 9], [9, 9], [9, 1], [1, 1]]},
                                           {"corners": []}], 5)
    name, text = msgs.foxglove_msgdef()
    path = tmp_path / "a.mcap"
    with path.open("wb") as f:
        w = Writer(f)
        schema = w.register_msgdef(name, text)
        for i, m in enumerate((msg, tags)):
            w.write_message("/a", schema, m, log_time=i, publish_time=i)
        w.finish()
    with AnyReader([path]) as reader:
        got = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()]
    assert [len(g.points) for g in got] == [len(g.texts) for g in got] == [1, 1]
    assert [(p.x, p.y) for p in got[0].points[0].points] == \
        [(5.4, 7.8), (15.6, 7.8), (15.6, 18.1), (5.4, 18.1)]
    assert got[0].points[0].type == 2  # LINE_LOOP: a closed outline
    assert got[0].texts[0].text == "crab 0.71"
    assert got[1].texts[0].text == "tag 7"
    assert [(p.x, p.y) for p in got[1].points[0].points] == [(1, 9), (9, 9), (9, 1), (1, 1)]
    assert (got[0].timestamp.sec, got[0].timestamp.nanosec) == (1_751_892_763, 120_000_000)


@pytest.mark.parametrize("rvec", [
    (0.0, 0.0, 0.0), (0.3, -0.2, 0.1), (np.pi, 0.0, 0.0), (0.0, np.pi, 0.0),
    (0.0, 0.0, np.pi), (np.pi / np.sqrt(2), np.pi / np.sqrt(2), 0.0), (-2.5, 1.0, 0.7),
])
def test_quaternion_rotates_as_opencvs_rotation_vector(rvec: tuple[float, ...]) -> None:
    r, _ = cv2.Rodrigues(np.array(rvec, np.float64))
    x, y, z, w = msgs.quaternion(r.tolist())
    angle = np.linalg.norm(rvec)
    if angle > 1e-12:  # the quaternion of a rotation vector: axis * sin(a/2), cos(a/2)
        axis = np.array(rvec) / angle
        ref = np.array([*(axis * np.sin(angle / 2)), np.cos(angle / 2)])
    else:
        ref = np.array([0.0, 0.0, 0.0, 1.0])
    got = np.array([x, y, z, w])
    assert np.allclose(got, ref, atol=1e-9) or np.allclose(got, -ref, atol=1e-9)
    assert w >= 0
