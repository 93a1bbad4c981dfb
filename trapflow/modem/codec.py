"""Compact link encoding of normalizer records, and its inverse at the surface.

A body is one kind byte, a varint bitmask of the fields present, then each field in
a fixed order with a fixed quantisation (confidence 0.005, pixels 0.1, rotation as a
rotation vector at 1e-4 rad, translation 1e-4, timestamps in ms). A record that does
not fit its kind's table is sent as msgpack (kind GENERIC); one too large for a frame even
so is refused by the sender, counted (`too_large`) and logged once per kind.
"""

from __future__ import annotations

import base64
import binascii
import calendar
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import msgspec
import numpy as np

from trapflow.config.modem import DEFAULT_LABELS
from trapflow.errors import ProtocolError
from trapflow.modem.frame import Reader, put_svarint, put_uvarint

GENERIC = 0x7F
_EPOCH_S = calendar.timegm((2020, 1, 1, 0, 0, 0, 0, 0, 0))


class _Unfit(Exception):
    """A value the kind's table cannot carry exactly enough: fall back to GENERIC."""


class _Ctx:
    def __init__(self, labels: Sequence[str]) -> None:
        self.labels = list(labels)
        self.index = {name: i for i, name in enumerate(self.labels)}


Enc = Callable[[bytearray, Any, _Ctx], None]
Dec = Callable[[Reader, _Ctx], Any]


def _num(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _Unfit
    return float(v)


def _fixed(scale: float) -> tuple[Enc, Dec]:
    digits = round(math.log10(scale))

    def enc(out: bytearray, v: Any, ctx: _Ctx) -> None:
        put_svarint(out, round(_num(v) * scale))

    def dec(r: Reader, ctx: _Ctx) -> Any:
        return round(r.svarint() / scale, digits)

    return enc, dec


def _fixed_list(scale: float, n: int) -> tuple[Enc, Dec]:
    one_enc, one_dec = _fixed(scale)

    def enc(out: bytearray, v: Any, ctx: _Ctx) -> None:
        if not isinstance(v, list) or len(v) != n:
            raise _Unfit
        for x in v:
            one_enc(out, x, ctx)

    def dec(r: Reader, ctx: _Ctx) -> Any:
        return [one_dec(r, ctx) for _ in range(n)]

    return enc, dec


def _enc_uint(out: bytearray, v: Any, ctx: _Ctx) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise _Unfit
    put_uvarint(out, v)


def _dec_uint(r: Reader, ctx: _Ctx) -> Any:
    return r.uvarint()


def _enc_bool(out: bytearray, v: Any, ctx: _Ctx) -> None:
    if not isinstance(v, bool):
        raise _Unfit
    out.append(int(v))


def _dec_bool(r: Reader, ctx: _Ctx) -> Any:
    return bool(r.take(1)[0])


def _enc_str(out: bytearray, v: Any, ctx: _Ctx) -> None:
    if not isinstance(v, str):
        raise _Unfit
    data = v.encode()
    put_uvarint(out, len(data))
    out += data


def _dec_str(r: Reader, ctx: _Ctx) -> Any:
    try:
        return r.take(r.uvarint()).decode()
    except UnicodeDecodeError:
        raise ProtocolError("expected UTF-8 text in a string field") from None


def _enc_label(out: bytearray, v: Any, ctx: _Ctx) -> None:
    if not isinstance(v, str):
        raise _Unfit
    if v in ctx.index:
        put_uvarint(out, ctx.index[v] + 1)
    else:
        out.append(0)
        _enc_str(out, v, ctx)


def _dec_label(r: Reader, ctx: _Ctx) -> Any:
    i = r.uvarint()
    if i == 0:
        return _dec_str(r, ctx)
    if i > len(ctx.labels):
        raise ProtocolError(f"expected a label index up to {len(ctx.labels)}, got {i}")
    return ctx.labels[i - 1]


def _enc_conf(out: bytearray, v: Any, ctx: _Ctx) -> None:
    q = round(_num(v) * 200)
    if not 0 <= q <= 255:
        raise _Unfit
    out.append(q)


def _dec_conf(r: Reader, ctx: _Ctx) -> Any:
    return round(r.take(1)[0] / 200, 3)


def _enc_ts(out: bytearray, v: Any, ctx: _Ctx) -> None:
    # "YYYY-MM-DD HH:MM:SS" with optional ".mmm": ms since 2020, low bit says ".mmm" present.
    if not isinstance(v, str) or len(v) not in (19, 23):
        raise _Unfit
    try:
        secs = calendar.timegm(time.strptime(v[:19], "%Y-%m-%d %H:%M:%S"))
        ms = int(v[20:]) if len(v) == 23 else 0
    except ValueError:
        raise _Unfit from None
    if len(v) == 23 and (v[19] != "." or not v[20:].isdigit()):
        raise _Unfit
    if secs < _EPOCH_S:
        raise _Unfit
    put_uvarint(out, ((secs - _EPOCH_S) * 1000 + ms) * 2 + (len(v) == 23))


def _dec_ts(r: Reader, ctx: _Ctx) -> Any:
    raw = r.uvarint()
    total_ms, has_ms = raw >> 1, raw & 1
    secs, ms = divmod(total_ms, 1000)
    text = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(_EPOCH_S + secs))
    return f"{text}.{ms:03d}" if has_ms else text


def _enc_secs(out: bytearray, v: Any, ctx: _Ctx) -> None:
    # "YYYY-MM-DD HH:MM:SS": whole seconds since 2020 (4 bytes until 2028, 5 after).
    if not isinstance(v, str) or len(v) != 19:
        raise _Unfit
    try:
        secs = calendar.timegm(time.strptime(v, "%Y-%m-%d %H:%M:%S"))
    except ValueError:
        raise _Unfit from None
    if secs < _EPOCH_S:
        raise _Unfit
    put_uvarint(out, secs - _EPOCH_S)


def _dec_secs(r: Reader, ctx: _Ctx) -> Any:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(_EPOCH_S + r.uvarint()))


def _enc_opt_id(out: bytearray, v: Any, ctx: _Ctx) -> None:
    # A track id, or None (not yet confirmed): id + 1, 0 for None.
    if v is None:
        out.append(0)
        return
    _enc_uint(out, v + 1 if isinstance(v, int) and not isinstance(v, bool) else -1, ctx)


def _dec_opt_id(r: Reader, ctx: _Ctx) -> Any:
    v = r.uvarint()
    return v - 1 if v else None


# A track's [length_m, range_m, speed_m_s] (None where not measured): centimetres,
# decimetres and cm/s as unsigned varints plus one (0: none), one byte each for a crab.
_MEASURED_SCALES = (100, 10, 100)


def _enc_measured(out: bytearray, v: Any, ctx: _Ctx) -> None:
    if not isinstance(v, list) or len(v) != len(_MEASURED_SCALES):
        raise _Unfit
    for x, scale in zip(v, _MEASURED_SCALES, strict=True):
        if x is None:
            out.append(0)
        elif (q := round(_num(x) * scale)) < 0:
            raise _Unfit
        else:
            put_uvarint(out, q + 1)


def _dec_measured(r: Reader, ctx: _Ctx) -> Any:
    return [(q - 1) / scale if (q := r.uvarint()) else None for scale in _MEASURED_SCALES]


def _enc_label_counts(out: bytearray, v: Any, ctx: _Ctx) -> None:
    # An interval's labels: count, then per label its name, visits, MaxN, dwell in seconds.
    if not isinstance(v, list):
        raise _Unfit
    put_uvarint(out, len(v))
    for lab in v:
        if not isinstance(lab, dict) or set(lab) != {"label", "visits", "max_n", "dwell_s"}:
            raise _Unfit
        _enc_label(out, lab["label"], ctx)
        for key in ("visits", "max_n"):
            _enc_uint(out, lab[key], ctx)
        put_uvarint(out, max(0, round(_num(lab["dwell_s"]))))


def _dec_label_counts(r: Reader, ctx: _Ctx) -> Any:
    return [{"label": _dec_label(r, ctx), "visits": r.uvarint(), "max_n": r.uvarint(),
             "dwell_s": r.uvarint()} for _ in range(r.uvarint())]


_NO_BOX = (0, 0, -1, -1)  # a `none` line's empty box: no real box has a negative extent


def _enc_box(out: bytearray, v: Any, ctx: _Ctx) -> None:
    if v == []:  # the detector saw nothing (label `none`): 4 bytes, not a generic record
        for q in _NO_BOX:
            put_svarint(out, q)
        return
    if not isinstance(v, list) or len(v) != 4:
        raise _Unfit
    x1, y1, x2, y2 = (round(_num(x) * 10) for x in v)
    if x2 < x1 or y2 < y1:  # an inverted box rides as it is, generic
        raise _Unfit
    for q in (x1, y1, x2 - x1, y2 - y1):
        put_svarint(out, q)


def _dec_box(r: Reader, ctx: _Ctx) -> Any:
    x1, y1, w, h = (r.svarint() for _ in range(4))
    if (x1, y1, w, h) == _NO_BOX:
        return []
    return [x1 / 10, y1 / 10, (x1 + w) / 10, (y1 + h) / 10]


def _enc_corners(out: bytearray, v: Any, ctx: _Ctx) -> None:
    if not isinstance(v, list) or len(v) != 4:
        raise _Unfit
    px = py = 0
    for pt in v:
        if not isinstance(pt, list) or len(pt) != 2:
            raise _Unfit
        x, y = round(_num(pt[0]) * 10), round(_num(pt[1]) * 10)
        put_svarint(out, x - px)
        put_svarint(out, y - py)
        px, py = x, y


def _dec_corners(r: Reader, ctx: _Ctx) -> Any:
    px = py = 0
    pts = []
    for _ in range(4):
        px += r.svarint()
        py += r.svarint()
        pts.append([px / 10, py / 10])
    return pts


def _rotvec(rot: np.ndarray) -> np.ndarray | None:
    """Rotation vector of a proper rotation matrix; None when rot is not one."""
    if np.abs(rot @ rot.T - np.eye(3)).max() > 1e-3 or np.linalg.det(rot) < 0:
        return None
    cos = max(-1.0, min(1.0, (np.trace(rot) - 1) / 2))
    angle = math.acos(cos)
    if angle < 1e-9:
        return np.zeros(3)
    if math.pi - angle < 1e-3:
        return None  # near 180 degrees the axis is ill-conditioned: send the matrix
    axis = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    return np.asarray(axis / (2 * math.sin(angle)) * angle)


def _matrix(vec: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(vec))
    if angle < 1e-12:
        return np.eye(3)
    k = vec / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.asarray(np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx)


def _put_rotation(out: bytearray, rot: np.ndarray) -> None:
    vec = _rotvec(rot)
    if vec is None:
        out.append(0)
        for x in rot.ravel():
            put_svarint(out, round(float(x) * 10000))
    else:
        out.append(1)
        for x in vec:
            put_svarint(out, round(float(x) * 10000))


def _get_rotation(r: Reader) -> list[float]:
    if r.take(1)[0]:
        rot = _matrix(np.array([r.svarint() / 10000 for _ in range(3)]))
        return [round(float(x), 4) for x in rot.ravel()]
    return [round(r.svarint() / 10000, 4) for _ in range(9)]


def _enc_rotation(out: bytearray, v: Any, ctx: _Ctx) -> None:
    if not isinstance(v, list) or len(v) != 9:
        raise _Unfit
    _put_rotation(out, np.array([_num(x) for x in v]).reshape(3, 3))


def _dec_rotation(r: Reader, ctx: _Ctx) -> Any:
    return _get_rotation(r)


def _enc_rt(out: bytearray, v: Any, ctx: _Ctx) -> None:
    if not isinstance(v, list) or len(v) != 3:
        raise _Unfit
    rows = []
    for row in v:
        if not isinstance(row, list) or len(row) != 4:
            raise _Unfit
        rows.append([_num(x) for x in row])
    m = np.array(rows)
    _put_rotation(out, m[:, :3])
    for x in m[:, 3]:
        put_svarint(out, round(float(x) * 10000))


def _dec_rt(r: Reader, ctx: _Ctx) -> Any:
    rot = _get_rotation(r)
    t = [round(r.svarint() / 10000, 4) for _ in range(3)]
    return [rot[0:3] + [t[0]], rot[3:6] + [t[1]], rot[6:9] + [t[2]]]


def _enc_pools(out: bytearray, v: Any, ctx: _Ctx) -> None:
    # {"mono": [rate_hz, drops], ...}
    if not isinstance(v, dict):
        raise _Unfit
    put_uvarint(out, len(v))
    for name, pair in v.items():
        if not isinstance(pair, list) or len(pair) != 2:
            raise _Unfit
        _enc_str(out, name, ctx)
        put_uvarint(out, max(0, round(_num(pair[0]) * 10)))
        _enc_uint(out, pair[1], ctx)


def _dec_pools(r: Reader, ctx: _Ctx) -> Any:
    pools = {}
    for _ in range(r.uvarint()):
        name = _dec_str(r, ctx)
        pools[name] = [r.uvarint() / 10, r.uvarint()]
    return pools


def _enc_records(out: bytearray, v: Any, ctx: _Ctx) -> None:
    if not isinstance(v, list):
        raise _Unfit
    put_uvarint(out, len(v))
    for rec in v:
        if not isinstance(rec, dict):
            raise _Unfit
        body = _encode(rec, ctx)
        put_uvarint(out, len(body))
        out += body


def _dec_records(r: Reader, ctx: _Ctx) -> Any:
    return [_decode(r.take(r.uvarint()), ctx) for _ in range(r.uvarint())]


def _enc_b64(out: bytearray, v: Any, ctx: _Ctx) -> None:
    # Bytes carried in a JSON record as base64 text: their length, then the bytes.
    if not isinstance(v, str):
        raise _Unfit
    try:
        data = base64.b64decode(v, validate=True)
    except (binascii.Error, ValueError):
        raise _Unfit from None
    put_uvarint(out, len(data))
    out += data


def _dec_b64(r: Reader, ctx: _Ctx) -> Any:
    return base64.b64encode(r.take(r.uvarint())).decode()


def _enc_calib(out: bytearray, v: Any, ctx: _Ctx) -> None:
    # A rig id (StereoRig.id): 8 hex digits ride as 4 bytes; anything else goes generic.
    if not isinstance(v, str) or len(v) != 8 or v != v.lower():
        raise _Unfit
    try:
        out += bytes.fromhex(v)
    except ValueError:
        raise _Unfit from None


def _dec_calib(r: Reader, ctx: _Ctx) -> Any:
    return r.take(4).hex()


CALIB = (_enc_calib, _dec_calib)
TS = (_enc_ts, _dec_ts)
UINT = (_enc_uint, _dec_uint)
BOOL = (_enc_bool, _dec_bool)
STR = (_enc_str, _dec_str)
LABEL = (_enc_label, _dec_label)
CONF = (_enc_conf, _dec_conf)
SECS = (_enc_secs, _dec_secs)
MM = _fixed(1000)  # metres to the millimetre
CM = _fixed(100)  # metres (or m/s) to the centimetre

# kind byte -> (record key, fields in wire order). Append only: the surface must agree.
KINDS: dict[int, tuple[str, list[tuple[str, tuple[Enc, Dec]]]]] = {
    1: ("mono_ir", [("timestamp", TS), ("seq", UINT), ("label", LABEL), ("confidence", CONF),
                    ("box", (_enc_box, _dec_box)), ("v", UINT), ("model", CALIB),
                    # appended for result lines v2: fields only append, old records decode
                    ("track", (_enc_opt_id, _dec_opt_id)), ("range_m", MM),
                    ("range_sd_m", MM), ("length_m", MM), ("length_sd_m", MM),
                    ("xyz", _fixed_list(1000, 3)), ("disparity_px", _fixed(100)),
                    ("length_method", STR), ("unmeasured", STR)]),
    2: ("stereo_ir", [("timestamp", TS), ("seq", UINT), ("label", LABEL), ("confidence", CONF),
                      ("calib", CALIB), ("v", UINT), ("model", CALIB)]),
    3: ("stereo_vo", [("timestamp", TS), ("seq", UINT), ("ok", BOOL), ("Rt", (_enc_rt, _dec_rt)),
                      ("inliers", UINT), ("calib", CALIB), ("v", UINT),
                      # appended (issue 26): without them every VO line went GENERIC, 320
                      # bytes, too large for a frame. The pose rides like Rt (rotation vector
                      # 1e-4 rad, translation 0.1 mm): about 47 bytes a line in all, so the
                      # surface reads the track itself, not composed from lines that may be lost.
                      ("pose", (_enc_rt, _dec_rt)), ("reinit", BOOL)]),
    4: ("tags", [("timestamp", TS), ("seq", UINT), ("id", UINT),
                 ("corners", (_enc_corners, _dec_corners)),
                 ("rotation", (_enc_rotation, _dec_rotation)),
                 ("translation", _fixed_list(10000, 3)), ("error", _fixed(1000)),
                 ("calib", CALIB), ("v", UINT)]),
    5: ("health", [("timestamp", TS), ("uptime_s", UINT), ("cpu_pct", _fixed(10)),
                   ("load1", _fixed(100)), ("temp_c", _fixed(10)), ("mem_pct", _fixed(10)),
                   ("disk_free_mb", UINT), ("backlog", UINT), ("link", STR),
                   ("pools", (_enc_pools, _dec_pools)), ("level", STR),
                   # appended (issue 25): the power model's watts at the host's CPU load
                   # now, and days on the configured battery at that draw, to 0.1
                   ("watts", _fixed(10)), ("days", _fixed(10)),
                   # appended (issue 33): the image-health state (learning, ok, fouled,
                   # turbid, fouled+turbid) and sharpness, contrast, brightness to the
                   # deployment's baseline, to 0.01
                   ("image", STR), ("image_ratio", _fixed_list(100, 3))]),
    6: ("aggregate", [("class", STR), ("from", TS), ("to", TS), ("count", UINT),
                      ("best", (_enc_records, _dec_records))]),
    # A finished track (trapflow.tracking.stage.modem_track). Common case, 12 bytes after
    # the kind byte: field mask 1, id 1, label 1, start 4, duration 1, confidence 1,
    # measured 3 (ids under 128, a label of the table, under two minutes, a crab's size).
    7: ("track", [("id", UINT), ("label", LABEL), ("start", SECS), ("duration_s", UINT),
                  ("confidence", CONF), ("measured", (_enc_measured, _dec_measured)),
                  ("pairs", UINT)]),
    8: ("counts", [("start", SECS), ("minutes", UINT), ("pairs", UINT),
                   ("labels", (_enc_label_counts, _dec_label_counts))]),
    # The run's news (trapflow.tracking.stage.modem_news), 8 bytes after the kind byte for
    # a label of the table and an id under 128: a label's first track, a new run-wide MaxN.
    9: ("new_label", [("label", LABEL), ("time", SECS), ("track", UINT)]),
    10: ("new_max_n", [("label", LABEL), ("time", SECS), ("max_n", UINT)]),
    # One packet of a queued track's thumbnail (trapflow.modem.thumb.record): its segments
    # from `first` on, with what rebuilds the header; 9 bytes besides them for a track id
    # under 128 (thumb.PACKET_OVERHEAD counts 10).
    11: ("thumb", [("track", UINT), ("first", UINT), ("width", UINT), ("height", UINT),
                   ("quality", UINT), ("shape", UINT), ("data", (_enc_b64, _dec_b64))]),
}  # fmt: skip
_BY_KEY = {key: (kind, fields) for kind, (key, fields) in KINDS.items()}


def _encode(record: dict[str, Any], ctx: _Ctx) -> bytes:
    if len(record) == 1:
        key, body = next(iter(record.items()))
        spec = _BY_KEY.get(key)
        if spec is not None and isinstance(body, dict):
            kind, fields = spec
            names = [name for name, _ in fields]
            if set(body) <= set(names):
                out = bytearray((kind,))
                put_uvarint(out, sum(1 << i for i, name in enumerate(names) if name in body))
                try:
                    for name, (enc, _) in fields:
                        if name in body:
                            enc(out, body[name], ctx)
                except _Unfit:
                    pass
                else:
                    return bytes(out)
    return bytes((GENERIC,)) + msgspec.msgpack.encode(record)


def _decode(data: bytes, ctx: _Ctx) -> dict[str, Any]:
    if not data:
        raise ProtocolError("expected a message body, got no bytes")
    if data[0] == GENERIC:
        try:
            value = msgspec.msgpack.decode(data[1:])
        except msgspec.DecodeError as exc:
            raise ProtocolError(f"expected a msgpack record: {exc}") from None
        if not isinstance(value, dict):
            raise ProtocolError(f"expected a msgpack map, got {type(value).__name__}")
        return value
    spec = KINDS.get(data[0])
    if spec is None:
        raise ProtocolError(
            f"expected a record kind in {sorted(KINDS)} or {GENERIC}, got {data[0]}"
        )
    key, fields = spec
    r = Reader(data[1:])
    mask = r.uvarint()
    body = {name: dec(r, ctx) for i, (name, (_, dec)) in enumerate(fields) if mask >> i & 1}
    if not r.done():
        raise ProtocolError(f"expected {r.pos} bytes of {key} body, got {len(r.data)}")
    return {key: body}


class LinkCodec:
    """Record dict <-> compact bytes; both ends must share the label table."""

    def __init__(self, labels: Sequence[str] = DEFAULT_LABELS) -> None:
        self._ctx = _Ctx(labels)

    def encode(self, record: dict[str, Any]) -> bytes:
        """Compact bytes for one record (never fails: GENERIC carries anything)."""
        return _encode(record, self._ctx)

    def decode(self, data: bytes) -> dict[str, Any]:
        """The record's JSON shape back; ProtocolError on malformed bytes."""
        try:
            return _decode(data, self._ctx)
        except (IndexError, ValueError, OverflowError) as exc:
            raise ProtocolError(f"expected a well-formed record body: {exc}") from None
