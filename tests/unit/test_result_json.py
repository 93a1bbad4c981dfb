"""The modem/disk JSON is a wire contract: golden lines and a size budget."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tests import builders
from trapflow.normalizer.result_json import (
    SCHEMA_VERSION,
    dumps,
    link_record,
    normalize,
    timestamp,
)
from trapflow.wire import messages

T = 1751892763120000000  # 2025-07-07 12:52:43.120 UTC

GOLDEN = [
    (messages.MonoIR(detections=[messages.Detection(label="crab", confidence=0.71234,
                                                    box=(5.43, 7.81, 15.6, 18.14))]),
     '{"mono_ir":{"timestamp":"2025-07-07 12:52:43.120","seq":7,"label":"crab",'
     '"confidence":0.712,"box":[5.4,7.8,15.6,18.1],"pool":"mono","v":3}}'),
    # Measured on the stereo pair: metres to the millimetre, the method named.
    (messages.MonoIR(detections=[messages.Detection(
        label="crab", confidence=0.9, box=(5.0, 7.0, 15.0, 18.0), range_m=1.23456,
        range_sd_m=0.01234, xyz=(0.1, -0.2, 1.2), disparity_px=97.6543, length_m=0.2004,
        length_sd_m=0.0081, length_method="endpoints")]),
     '{"mono_ir":{"timestamp":"2025-07-07 12:52:43.120","seq":7,"label":"crab",'
     '"confidence":0.9,"box":[5.0,7.0,15.0,18.0],"range_m":1.235,"range_sd_m":0.012,'
     '"length_m":0.2,"length_sd_m":0.008,"xyz":[0.1,-0.2,1.2],"disparity_px":97.65,'
     '"length_method":"endpoints","pool":"mono","v":3}}'),
    # Not measured: no numbers, the reason instead.
    (messages.MonoIR(detections=[messages.Detection(
        label="crab", confidence=0.9, box=(5.0, 7.0, 15.0, 18.0), unmeasured="out_of_view")]),
     '{"mono_ir":{"timestamp":"2025-07-07 12:52:43.120","seq":7,"label":"crab",'
     '"confidence":0.9,"box":[5.0,7.0,15.0,18.0],"unmeasured":"out_of_view","pool":"mono","v":3}}'),
    (messages.MonoIR(),
     '{"mono_ir":{"timestamp":"2025-07-07 12:52:43.120","seq":7,"label":"none",'
     '"confidence":0.0,"box":[],"pool":"mono","v":3}}'),
    (messages.StereoIR(label="scallop", confidence=0.9),
     '{"stereo_ir":{"timestamp":"2025-07-07 12:52:43.120","seq":7,"label":"scallop",'
     '"confidence":0.9,"pool":"mono","v":3}}'),
    (messages.StereoVO(ok=True, rotation=(1, 0, 0, 0, 1, 0, 0, 0, 1), translation=(0.1, 0, 0.25),
                       inliers=120),
     '{"stereo_vo":{"timestamp":"2025-07-07 12:52:43.120","seq":7,"ok":true,"inliers":120,'
     '"Rt":[[1.0,0.0,0.0,0.1],[0.0,1.0,0.0,0.0],[0.0,0.0,1.0,0.25]],"pool":"mono","v":3}}'),
    (messages.StereoVO(ok=False, reinit=True),
     '{"stereo_vo":{"timestamp":"2025-07-07 12:52:43.120","seq":7,"ok":false,"inliers":0,'
     '"reinit":true,"pool":"mono","v":3}}'),
    (messages.Extra(name="brightness", fields={"mean": 0.123456, "n": 3}),
     '{"brightness":{"timestamp":"2025-07-07 12:52:43.120","seq":7,"mean":0.123,"n":3,'
     '"pool":"mono","v":3}}'),
]


def test_golden_lines() -> None:
    for body, line in GOLDEN:
        out = [dumps(o).decode() for o in normalize(builders.result(body, t_wall_ns=T))]
        assert out == [line]
        assert json.loads(line)  # and it is JSON, numbers as numbers


def test_one_object_per_detection_and_tag() -> None:
    dets = [messages.Detection(label="crab", confidence=0.5, box=(0, 0, 1, 1))] * 3
    assert len(normalize(builders.result(messages.MonoIR(detections=dets)))) == 3
    tags = messages.Tags(tags=[messages.Tag(id=i, corners=[(0, 0)] * 4) for i in range(2)])
    out = normalize(builders.result(tags))
    assert [o["tags"]["id"] for o in out] == [0, 1]


def test_size_budget() -> None:
    """A detection line stays small enough for an acoustic modem's store-and-forward: as JSON
    on disk, and far smaller in the link codec, where the schema version and the model hash
    (4 bytes) cost 6 bytes together."""
    from trapflow.modem.codec import LinkCodec

    body = messages.MonoIR(detections=[messages.Detection(
        label="crab", confidence=0.712345678, box=(1234.5678, 718.123, 1279.99, 719.99))],
        model="0a1b2c3d")
    obj = normalize(builders.result(body, seq=10**9))[0]
    line = dumps(obj)
    assert len(line) <= 180, line  # 165 before lines named their pool (14 bytes for "mono")
    codec = LinkCodec()
    sent = link_record(obj)
    bare = {"mono_ir": {k: v for k, v in sent["mono_ir"].items() if k not in ("v", "model")}}
    assert len(codec.encode(sent)) <= len(codec.encode(bare)) + 6
    back = codec.decode(codec.encode(sent))["mono_ir"]
    assert (back["v"], back["model"]) == (SCHEMA_VERSION, "0a1b2c3d")


def test_every_line_carries_the_schema_version_and_onnx_lines_the_model_hash() -> None:
    bodies = [messages.MonoIR(model="0a1b2c3d"), messages.StereoIR(label="x", confidence=1,
                                                                  model="0a1b2c3d"),
              messages.StereoVO(ok=False), messages.Tags(),
              messages.Extra(name="brightness", fields={"mean": 1.0})]
    for body in bodies:
        (obj,) = normalize(builders.result(body))
        (item,) = obj.values()
        assert item["v"] == SCHEMA_VERSION
        assert item.get("model") == getattr(body, "model", None)


def test_timestamp_is_utc_with_millis() -> None:
    assert timestamp(T) == "2025-07-07 12:52:43.120"


def test_a_pair_without_tags_writes_one_line() -> None:
    """Regression (issue 12): a pair the tags pool processed and found no tag in wrote no line,
    so "processed, nothing found" could not be told from "not processed"."""
    out = [dumps(o).decode() for o in normalize(builders.result(messages.Tags(), t_wall_ns=T))]
    assert out == ['{"tags":{"timestamp":"2025-07-07 12:52:43.120","seq":7,"corners":[],'
                   '"pool":"mono","v":3}}']


def test_stereo_results_carry_the_rig_id() -> None:
    """Every stereo line names the calibration it was computed with; mono lines do not."""
    bodies = [
        messages.StereoIR(label="scallop", confidence=0.9, calib="0a1b2c3d"),
        messages.StereoVO(ok=False, calib="0a1b2c3d"),
        messages.Tags(tags=[messages.Tag(id=i, corners=[(0, 0)] * 4) for i in range(2)],
                      calib="0a1b2c3d"),
    ]
    for body in bodies:
        objs = normalize(builders.result(body))
        assert objs and all(next(iter(o.values()))["calib"] == "0a1b2c3d" for o in objs)
    mono = normalize(builders.result(messages.MonoIR()))
    assert "calib" not in mono[0]["mono_ir"]
    assert "calib" not in normalize(builders.result(messages.StereoVO(ok=False)))[0]["stereo_vo"]


def _vo_body(angle: float, t: tuple[float, float, float]) -> messages.StereoVO:
    c, s = math.cos(angle), math.sin(angle)
    rot = (c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
    pose = (c, -s, 0.0, t[0] * 7, s, c, 0.0, t[1] * 7, 0.0, 0.0, 1.0, t[2] * 7)
    return messages.StereoVO(ok=True, rotation=rot, translation=t, pose=pose, inliers=50)


@pytest.mark.parametrize("decimals", [0, 3, 9])
def test_each_quantity_keeps_its_precision_whatever_decimals(decimals: int) -> None:
    """Regression: `normalizer.decimals: 3` rounded VO's Rt to 5 decimals and its pose to 1 mm,
    so integrating results.jsonl gave 8x VO's rotational drift. `decimals` now rounds only the
    plugin-defined (Extra) fields; built-in quantities keep what they need."""
    vo = _vo_body(1.234567891e-4, (0.012345678912, -0.00098765432101, 0.33333333333))
    out = normalize(builders.result(vo), decimals)[0]["stereo_vo"]
    rt = np.array(out["Rt"])
    np.testing.assert_allclose(rt[:, :3].ravel(), vo.rotation, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rt[:, 3], vo.translation, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.ravel(out["pose"]), vo.pose, rtol=0, atol=1e-9)
    tag = messages.Tag(id=3, corners=[(10.04, 20.06)] * 4, rotation=vo.rotation,
                       translation=vo.translation, error=0.123456)
    t = normalize(builders.result(messages.Tags(tags=[tag])), decimals)[0]["tags"]
    np.testing.assert_allclose(t["rotation"], vo.rotation, rtol=0, atol=1e-9)
    np.testing.assert_allclose(t["translation"], vo.translation, rtol=0, atol=1e-9)
    assert t["corners"][0] == [10.0, 20.1] and t["error"] == 0.123
    det = messages.Detection(label="crab", confidence=0.987654, box=(1.26, 2.34, 3.45, 4.44))
    m = normalize(builders.result(messages.MonoIR(detections=[det])), decimals)[0]["mono_ir"]
    assert m["confidence"] == 0.988 and m["box"] == [1.3, 2.3, 3.5, 4.4]
    s = normalize(builders.result(messages.StereoIR(label="x", confidence=0.98765)), decimals)
    assert s[0]["stereo_ir"]["confidence"] == 0.988
    extra = messages.Extra(name="b", fields={"mean": 0.123456789123})
    assert normalize(builders.result(extra), decimals)[0]["b"]["mean"] == round(0.123456789123,
                                                                                decimals)


def test_every_line_names_its_pool_and_the_link_leaves_it_out() -> None:
    """Two pools may run one plugin (a local and a remote digest pool): the line names its
    pool, since its kind does not. The modem carries the line without it, in its kind's
    table as before (the `pool` key alone would have sent it generic), so the link's bytes
    are what they were."""
    from tests.unit.test_results_schema import SHAPES
    from trapflow.modem.codec import GENERIC, KINDS, LinkCodec

    codec, tables = LinkCodec(), {key: {name for name, _c in fields}
                                  for key, fields in KINDS.values()}
    for shapes in SHAPES.values():
        for body in shapes:
            for obj in normalize(builders.result(body, pool="mono_b")):
                (kind, item), = obj.items()
                assert item["pool"] == "mono_b" and list(item)[-2:] == ["pool", "v"]
                sent = link_record(obj)
                assert sent[kind] == {k: v for k, v in item.items() if k != "pool"}
                if kind in tables:  # every key the link carries is in its kind's table
                    assert set(sent[kind]) <= tables[kind], (kind, set(sent[kind]) - tables[kind])
                    assert "pool" not in tables[kind]
                else:  # a plugin's kind travels generic, as before
                    assert codec.encode(sent)[0] == GENERIC
