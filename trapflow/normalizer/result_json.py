"""Results -> compact JSON objects, the wire contract of the modem and results.jsonl.

Shape: {"mono_ir": {"timestamp": "2025-07-07 12:52:43.120", "seq": 17, "label": "crab",
"confidence": 0.71, "box": [5.4, 7.8, 15.6, 18.1], "pool": "mono", "v": 3}} -- numbers as
numbers, UTC times. Every line names `pool`, the pool whose result it is (two pools may run
one plugin, so a line's kind does not say which pool made it), and ends with `v`, the
version of this shape (SCHEMA_VERSION: raised when the keys a line carries change: one added,
gone or meaning another thing); lines of ONNX-based pools also carry `model`, the short hash
of the model file that produced them. The modem carries every key of a line but `pool`
(link_record): the surface knows results by kind, and the pool would cost a frame its bytes.
Each quantity keeps the precision it needs, whatever the modem's codec later quantises:
confidences 1e-3, pixels 0.1, rotations and translations (VO's `Rt` and `pose`, tag poses) 1e-9.
"""

from __future__ import annotations

import datetime as dt
from typing import Any

import msgspec

from trapflow.wire import messages

_json = msgspec.json.Encoder()
SCHEMA_VERSION = 3
"""2: detection lines carry `track` (their track's id, null until confirmed) and, where the
stereo pair measured them, range_m, range_sd_m, xyz, disparity_px, length_m, length_sd_m,
length_method, or `unmeasured` with the reason. 3: every line carries `pool`."""
POOL_KEY = "pool"
"""The key of a line that names the pool whose result it is (lines of v2 and before lack it:
readers then fall back to the pool that ledger.json or the normalizer's routes give its kind)."""

CONFIDENCE_DIGITS = 3
"""Scores: 1e-3 is finer than any threshold a user sets."""
PIXEL_DIGITS = 1
"""Boxes and corners: 0.1 px, as the modem carries them."""
POSE_DIGITS = 9
"""Rotation elements and translations in metres. Readers compose VO's `Rt` rows: at 5
decimals the composed pose of a short run strayed 4e-5 from the worker's own and stopped being
a rotation; at 1e-9 it stays within 1e-6 of it for a thousand steps and more."""
ERROR_DIGITS = 3
"""A tag's reprojection error in pixels."""
METRE_DIGITS = 3
"""Ranges, positions and lengths of animals: 1 mm, finer than any stereo rig here measures."""


def timestamp(t_wall_ns: int) -> str:
    """UTC wall-clock label with milliseconds: '2025-07-07 12:52:43.120'."""
    t = dt.datetime.fromtimestamp(t_wall_ns / 1e9, tz=dt.timezone.utc)
    return t.strftime("%Y-%m-%d %H:%M:%S.") + f"{t.microsecond // 1000:03d}"


def parse_timestamp(text: str) -> int:
    """The wall-clock ns of a line's `timestamp` (to the millisecond it carries)."""
    t = dt.datetime.strptime(text, "%Y-%m-%d %H:%M:%S.%f").replace(tzinfo=dt.timezone.utc)
    return int(t.timestamp()) * 10**9 + t.microsecond * 1000


def _r(x: float, nd: int) -> float:
    return round(float(x), nd)


def _rows(values: tuple[float, ...], nd: int) -> list[list[float]]:
    return [[_r(v, nd) for v in values[i : i + 4]] for i in range(0, len(values), 4)]


def normalize(res: messages.Result, decimals: int = 3) -> list[dict[str, Any]]:
    """One JSON-able object per reported item of a result (one per detection or tag).

    Stereo results also carry `calib`, the id of the rig they were computed with; every line
    `pool`, the pool whose result it is. `decimals` (`normalizer.decimals`) rounds only the
    float fields of plugin-defined results (Extra), whose quantities trapflow does not know;
    built-in fields keep their own precision.
    """
    objs = _items(res, decimals)
    calib = getattr(res.body, "calib", "")
    model = getattr(res.body, "model", "")
    for obj in objs:
        for item in obj.values():
            if calib:
                item["calib"] = calib
            if model:
                item["model"] = model
            item[POOL_KEY] = res.pool
            item["v"] = SCHEMA_VERSION
    return objs


def link_record(obj: dict[str, Any]) -> dict[str, Any]:
    """A line as the modem carries it: without `pool` (the link codec's tables hold every
    other key of a built-in kind, so its bytes are what they were before lines named it)."""
    return {kind: {k: v for k, v in item.items() if k != POOL_KEY} if isinstance(item, dict)
            else item for kind, item in obj.items()}


def _items(res: messages.Result, decimals: int) -> list[dict[str, Any]]:
    base: dict[str, Any] = {"timestamp": timestamp(res.t_wall_ns), "seq": res.seq}
    b = res.body
    nd = decimals
    cd, pd = CONFIDENCE_DIGITS, POSE_DIGITS
    if isinstance(b, messages.MonoIR):
        if not b.detections:
            return [{"mono_ir": {**base, "label": "none", "confidence": 0.0, "box": []}}]
        return [
            {"mono_ir": {**base, "label": d.label, "confidence": _r(d.confidence, cd),
                         "box": [_r(v, PIXEL_DIGITS) for v in d.box], **_measured(d)}}
            for d in b.detections
        ]
    if isinstance(b, messages.StereoIR):
        return [{"stereo_ir": {**base, "label": b.label, "confidence": _r(b.confidence, cd)}}]
    if isinstance(b, messages.StereoVO):
        out: dict[str, Any] = {**base, "ok": b.ok, "inliers": b.inliers}
        if b.ok and len(b.rotation) == 9:
            r, t = b.rotation, b.translation
            rt = (*r[0:3], t[0], *r[3:6], t[1], *r[6:9], t[2])
            out["Rt"] = _rows(rt, pd)
        if len(b.pose) == 12:
            out["pose"] = _rows(b.pose, pd)
        if b.reinit:
            out["reinit"] = True
        return [{"stereo_vo": out}]
    if isinstance(b, messages.Tags):
        if not b.tags:  # processed, nothing seen: one line, so it differs from "not processed"
            return [{"tags": {**base, "corners": []}}]
        return [
            {"tags": {**base, "id": t.id, "corners": [[_r(x, 1), _r(y, 1)] for x, y in t.corners],
                      "rotation": [_r(v, pd) for v in t.rotation],
                      "translation": [_r(v, pd) for v in t.translation],
                      "error": _r(t.error, ERROR_DIGITS)}}
            for t in b.tags
        ]
    if isinstance(b, messages.Extra):
        fields = {k: (_r(v, nd) if isinstance(v, float) else v) for k, v in b.fields.items()}
        return [{b.name: {**base, **fields}}]
    raise TypeError(f"unknown result body {type(b).__name__}")


def _measured(d: messages.Detection) -> dict[str, Any]:
    """A detection's stereo measurement keys (millimetres kept), or its reason code."""
    if d.range_m is None:
        return {"unmeasured": d.unmeasured} if d.unmeasured else {}
    out: dict[str, Any] = {"range_m": _r(d.range_m, METRE_DIGITS)}
    for key in ("range_sd_m", "length_m", "length_sd_m"):
        value = getattr(d, key)
        if value is not None:
            out[key] = _r(value, METRE_DIGITS)
    if d.xyz is not None:
        out["xyz"] = [_r(v, METRE_DIGITS) for v in d.xyz]
    if d.disparity_px is not None:
        out["disparity_px"] = _r(d.disparity_px, 2)
    if d.length_method:
        out["length_method"] = d.length_method
    return out


def dumps(obj: dict[str, Any]) -> bytes:
    """Compact JSON bytes, no spaces, no newline."""
    return _json.encode(obj)
