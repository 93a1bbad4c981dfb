"""The lines a run writes, typed: one Struct per result kind of results.jsonl, and the lines
of tracks.jsonl and counts.jsonl. The one definition of their keys: readers decode a line
here and take its fields, never a string key of a parsed dict, so a renamed key fails where
it is decoded, with the file's line and what was wrong.

A results.jsonl line is `{"<kind>": {...}}`; its body names the pool whose result it is
(`pool`, from schema v3) and ends with `v`. The builder (trapflow.normalizer.result_json)
still writes dicts, on the normalizer's path; `encode_result` of a decoded line gives back
exactly the bytes it wrote (the field order below is the order it writes them in, an absent
key is UNSET), so the schema version moves only where the bytes change.

Each field's `Meta` holds its row of the results.jsonl table of docs/results.md (when it is
there, its type and unit, what it means): `doc_rows` renders the table from them, and a unit
test holds the document to it.
"""

from __future__ import annotations

from typing import Annotated, Any, NamedTuple, Union

import msgspec
from msgspec import UNSET, Meta, UnsetType

from trapflow.errors import ProtocolError


def _doc(present: str, kind: str, meaning: str) -> Meta:
    """A field's row of the docs table: when it is there, its type and unit, its meaning."""
    return Meta(description=meaning, extra={"present": present, "type": kind})


class LineError(ProtocolError):
    """A line that is not a line of its file: which line, and what was wrong."""


class OtherKind(LineError):
    """A whole line of another kind than the file's (a reader may pass it by)."""


# Keys every result kind carries, with one meaning.
Timestamp = Annotated[str, _doc("always", "string, UTC",
                                "capture time of the pair, `YYYY-MM-DD HH:MM:SS.mmm`")]
Seq = Annotated[int, _doc("always", "integer", "the pair's number in the run")]
Pool = Annotated[str | UnsetType, _doc(
    "always", "string",
    "the pool whose result it is (`pools:` in the config): two pools may run one plugin, and "
    "`ledger.json` counts each pool's lines by it; not carried by the modem")]
Version = Annotated[int | UnsetType, _doc(
    "always", "integer",
    "version of this schema (raised when the keys change: one added, gone or meaning another "
    "thing; 2 since `track` and the measurements, 3 since `pool`)")]
Rows = list[list[float]]


class Line(msgspec.Struct, kw_only=True):
    """Base of every typed line (mutable: re-analysis sets a detection's `track`)."""


class MonoIRLine(Line, kw_only=True):
    """One detection of a mono detector (`mono_ir`), or its pair's `none` line."""

    timestamp: Timestamp
    seq: Seq
    label: Annotated[str, _doc("always", "string",
                               "the detection's class; `none` when nothing was detected")]
    confidence: Annotated[float, _doc("always", "number, 0..1 (1e-3)",
                                      "the detection's score; 0 with `none`")]
    box: Annotated[list[float], _doc("always", "[x1, y1, x2, y2], pixels (0.1)",
                                     "the box in the left image; `[]` with `none`")]
    range_m: Annotated[float | UnsetType, _doc(
        "measured", "number, metres (1e-3)",
        "distance from the left camera to the animal, from the stereo pair")] = UNSET
    range_sd_m: Annotated[float | UnsetType, _doc(
        "measured", "number, metres (1e-3)",
        "its standard deviation (disparity spread and calibration)")] = UNSET
    length_m: Annotated[float | UnsetType, _doc(
        "measured", "number, metres (1e-3)", "the animal's length along its major axis")] = UNSET
    length_sd_m: Annotated[float | UnsetType, _doc(
        "measured", "number, metres (1e-3)", "its standard deviation")] = UNSET
    xyz: Annotated[list[float] | UnsetType, _doc(
        "measured", "[x, y, z], metres (1e-3)",
        "the animal's centre in the left camera frame")] = UNSET
    disparity_px: Annotated[float | UnsetType, _doc(
        "measured", "number, pixels (0.01)", "its disparity between the two images")] = UNSET
    length_method: Annotated[str | UnsetType, _doc(
        "measured", "string",
        "`endpoints` (the box's two ends along its longer centre line, each triangulated at "
        "the disparity of the plane the animal lies on: the box's own, combined with the "
        "floor's plane fitted over the whole pair) or `box` (the box's extent at the range, "
        "where neither plane could be measured)")] = UNSET
    unmeasured: Annotated[str | UnsetType, _doc(
        "not measured", "string",
        "why no numbers: `out_of_view`, `textureless`, `ambiguous`, `low_score`, "
        "`bad_box`")] = UNSET
    model: Annotated[str | UnsetType, _doc(
        "ONNX models", "string", "short hash of the model file that detected it")] = UNSET
    pool: Pool = UNSET
    track: Annotated[int | None | UnsetType, _doc(
        "with a box", "integer or null",
        "id of the animal's track (`tracks.jsonl`); null until the track is confirmed "
        "(`observe.min_hits`) or for a box that starts none")] = UNSET
    v: Version = UNSET


class StereoIRLine(Line, kw_only=True):
    """A stereo classifier's verdict on one pair (`stereo_ir`)."""

    timestamp: Timestamp
    seq: Seq
    label: Annotated[str, _doc("always", "string", "the pair's class; `none` below the "
                                                   "threshold")]
    confidence: Annotated[float, _doc("always", "number, 0..1 (1e-3)", "its score")]
    calib: Annotated[str | UnsetType, _doc(
        "always", "string, 8 hex digits",
        "id of the stereo rig the pair was taken with")] = UNSET
    model: Annotated[str | UnsetType, _doc(
        "ONNX models", "string", "short hash of the model file that classified it")] = UNSET
    pool: Pool = UNSET
    v: Version = UNSET


class StereoVOLine(Line, kw_only=True):
    """Visual odometry of one pair (`stereo_vo`)."""

    timestamp: Timestamp
    seq: Seq
    ok: Annotated[bool, _doc("always", "boolean", "whether the motion of this pair was "
                                                  "measured")]
    inliers: Annotated[int, _doc("always", "integer", "features that agreed on the motion")]
    Rt: Annotated[Rows | UnsetType, _doc(
        "when `ok`", "3x4 rows, metres (1e-9)",
        "motion since the last ok pair: rotation (3x3) and translation (last column) "
        "together")] = UNSET
    pose: Annotated[Rows | UnsetType, _doc(
        "once tracking", "3x4 rows, metres (1e-9)",
        "the left camera in the frame of the first pair (camera to world); "
        "`pose = previous pose @ Rt`")] = UNSET
    reinit: Annotated[bool | UnsetType, _doc(
        "when true", "boolean", "tracking started again here (after a gap or lost "
                                "pairs)")] = UNSET
    calib: Annotated[str | UnsetType, _doc(
        "always", "string, 8 hex digits", "id of the rig VO computed with")] = UNSET
    pool: Pool = UNSET
    v: Version = UNSET


class TagsLine(Line, kw_only=True):
    """One fiducial tag seen in a pair (`tags`), or its pair's line of none seen."""

    timestamp: Timestamp
    seq: Seq
    id: Annotated[int | UnsetType, _doc("a tag seen", "integer",
                                        "the tag's id in its family")] = UNSET
    corners: Annotated[Rows, _doc("always", "[[x, y] x 4], pixels (0.1)",
                                  "the tag's corners in the left image; `[]` when no tag was "
                                  "seen")]
    rotation: Annotated[list[float] | UnsetType, _doc(
        "a tag seen", "9 numbers, row major (1e-9)", "tag to camera rotation")] = UNSET
    translation: Annotated[list[float] | UnsetType, _doc(
        "a tag seen", "3 numbers, metres (1e-9)", "tag centre in the camera frame")] = UNSET
    error: Annotated[float | UnsetType, _doc(
        "a tag seen", "number, pixels (1e-3)", "reprojection error of the pose")] = UNSET
    calib: Annotated[str | UnsetType, _doc(
        "always", "string, 8 hex digits",
        "id of the rig the poses were computed with")] = UNSET
    pool: Pool = UNSET
    v: Version = UNSET


class PluginLine(Line, kw_only=True):
    """A third-party plugin's result (its kind is the plugin's name): the keys every line
    carries, and the plugin's own `fields` in the order it wrote them (between `seq` and
    `pool` in the line)."""

    timestamp: Timestamp
    seq: Seq
    fields: dict[str, Any] = {}
    pool: Pool = UNSET
    v: Version = UNSET


ResultItem = Union[MonoIRLine, StereoIRLine, StereoVOLine, TagsLine, PluginLine]
KINDS: dict[str, type[MonoIRLine | StereoIRLine | StereoVOLine | TagsLine]] = {
    "mono_ir": MonoIRLine, "stereo_ir": StereoIRLine, "stereo_vo": StereoVOLine,
    "tags": TagsLine}
"""The built-in result kinds; any other kind is a plugin's (PluginLine)."""
PLUGIN_DOC = ("`timestamp`, `seq`, `pool`, `v`", "always", "as above",
              "as above, then the plugin's own fields (floats rounded to "
              "`normalizer.decimals`)")
"""The plugin row of the docs table: its own fields are the plugin's to document."""
_PLUGIN_KEYS = ("timestamp", "seq", "pool", "v")


class ResultLine(NamedTuple):
    """A decoded results.jsonl line: its kind and its typed body."""

    kind: str
    item: ResultItem

    @property
    def pool(self) -> str | None:
        """The pool the line names, or None (a line of v2 or before)."""
        return self.item.pool if isinstance(self.item.pool, str) else None


# --- tracks.jsonl and counts.jsonl ---------------------------------------------------


class TrackLine(Line, kw_only=True):
    """A finished track, the body of a tracks.jsonl line `{"track": {...}}`
    (docs/observations.md)."""

    id: Annotated[int, Meta(description="the track's id, from 1 in the run per detector "
                                        "pool, as on its detection lines")]
    label: Annotated[str, Meta(description="the label most of its boxes carried")]
    label_share: Annotated[float, Meta(description="share (0-1) of its boxes with `label`")]
    first_s: Annotated[float, Meta(description="capture time (UTC seconds) of its first box")]
    last_s: Annotated[float, Meta(description="capture time (UTC seconds) of its last box")]
    pairs: Annotated[int, Meta(description="pairs in which it was detected")]
    best_confidence: Annotated[float, Meta(description="its most confident box's confidence")]
    best_box: Annotated[list[float], Meta(description="its most confident box, "
                                                      "[x1, y1, x2, y2] in pixels")]
    path: Annotated[Rows, Meta(description="up to 32 [t_s, cx, cy] box centres (UTC seconds, "
                                           "pixels), evenly spaced, the last box included")]
    duration_s: Annotated[float, Meta(description="last_s - first_s, seconds")]
    range_m: Annotated[float | UnsetType, Meta(
        description="stereo: range at its first measured box, metres")] = UNSET
    position_radius_m: Annotated[float | UnsetType, Meta(
        description="stereo: Camtrap DP position, distance from the camera axis")] = UNSET
    position_angle_deg: Annotated[float | UnsetType, Meta(
        description="stereo: Camtrap DP position, angle from the camera axis, positive to "
                    "the right")] = UNSET
    length_m: Annotated[float | UnsetType, Meta(
        description="stereo: median length of the sharpest half of its measured boxes")] = UNSET
    length_spread_m: Annotated[float | UnsetType, Meta(
        description="stereo: their spread")] = UNSET
    length_views: Annotated[int | UnsetType, Meta(
        description="stereo: how many lengths the median took")] = UNSET
    speed_m_s: Annotated[float | UnsetType, Meta(
        description="stereo: speed along its 3-D path (path length over time)")] = UNSET
    speed_sd_m_s: Annotated[float | UnsetType, Meta(
        description="stereo: how that speed varied from step to step")] = UNSET
    net_speed_m_s: Annotated[float | UnsetType, Meta(
        description="stereo: the speed of its net displacement")] = UNSET
    speed_frame: Annotated[str | UnsetType, Meta(
        description="`ground` (VO's world frame) or `camera` (the rig taken to stand "
                    "still)")] = UNSET


class LabelCountLine(Line, kw_only=True):
    """One label's numbers in one interval of counts.jsonl."""

    label: Annotated[str, Meta(description="the tracks' label (their tracks.jsonl label)")]
    visits: Annotated[int, Meta(description="tracks confirmed in the interval")]
    max_n: Annotated[int, Meta(description="most tracks of the label at one capture time")]
    dwell_s: Annotated[float, Meta(description="summed time its tracks were seen, seconds")]


class CountsLine(Line, kw_only=True):
    """A closed counting interval, the body of a counts.jsonl line `{"counts": {...}}`."""

    start_s: Annotated[float, Meta(description="the interval's start, UTC seconds")]
    end_s: Annotated[float, Meta(description="its end (the run's last pair for the last)")]
    pairs: Annotated[int, Meta(description="the effort: pairs the detector saw in it")]
    labels: Annotated[list[LabelCountLine], Meta(description="every label with a track in it")]


TRACK_KEY, COUNTS_KEY = "track", "counts"
"""The one key of a tracks.jsonl and of a counts.jsonl line."""

# --- decoding and encoding -----------------------------------------------------------

_envelope = msgspec.json.Decoder(dict[str, msgspec.Raw])
_decoders = {kind: msgspec.json.Decoder(cls) for kind, cls in KINDS.items()}
_plugin = msgspec.json.Decoder(dict[str, Any])
_track = msgspec.json.Decoder(TrackLine)
_counts = msgspec.json.Decoder(CountsLine)
_json = msgspec.json.Encoder()


def _one(line: bytes | str, where: str) -> tuple[str, msgspec.Raw]:
    try:
        obj = _envelope.decode(line)
    except msgspec.DecodeError as exc:
        raise LineError(f"{where}: expected a JSON object of one kind, {exc}") from None
    if len(obj) != 1:
        raise LineError(f"{where}: expected a JSON object of one kind, got "
                        f"{len(obj)} keys ({', '.join(sorted(obj)) or 'none'})")
    (kind, raw), = obj.items()
    return kind, raw


def _plugin_item(kind: str, raw: msgspec.Raw) -> PluginLine:
    body = _plugin.decode(raw)
    base = {k: body.pop(k) for k in _PLUGIN_KEYS if k in body}
    return msgspec.convert({**base, "fields": body}, PluginLine)


def decode_result(line: bytes | str, where: str = "results.jsonl line") -> ResultLine:
    """One results.jsonl line (without or with its newline) as its kind and typed body;
    LineError naming `where` (the file and line) and what was wrong otherwise."""
    kind, raw = _one(line, where)
    try:
        dec = _decoders.get(kind)
        return ResultLine(kind, dec.decode(raw) if dec is not None else _plugin_item(kind, raw))
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise LineError(f"{where}: {kind}: {exc}") from None


def result_item(kind: str, body: dict[str, Any]) -> ResultItem:
    """A line's body already parsed (a record the modem carried, a dict of the builder)
    as its kind's Struct; LineError when it is not one."""
    try:
        cls = KINDS.get(kind)
        if cls is not None:
            return msgspec.convert(body, cls)
        base = {k: body[k] for k in _PLUGIN_KEYS if k in body}
        rest = {k: v for k, v in body.items() if k not in _PLUGIN_KEYS}
        return msgspec.convert({**base, "fields": rest}, PluginLine)
    except msgspec.ValidationError as exc:
        raise LineError(f"{kind}: {exc}") from None


def result_body(item: ResultItem) -> dict[str, Any]:
    """The body as the builder makes it: a dict, its keys in the line's order."""
    if isinstance(item, PluginLine):
        out: dict[str, Any] = {"timestamp": item.timestamp, "seq": item.seq, **item.fields}
        for key, value in (("pool", item.pool), ("v", item.v)):
            if value is not UNSET:
                out[key] = value
        return out
    built: dict[str, Any] = msgspec.to_builtins(item)
    return built


def encode_result(kind: str, item: ResultItem) -> bytes:
    """The line's bytes as results.jsonl holds them (no newline): those it was decoded from,
    for every line the builder writes."""
    if isinstance(item, PluginLine):
        return _json.encode({kind: result_body(item)})
    return _json.encode({kind: item})


def decode_track(line: bytes | str, where: str = "tracks.jsonl line") -> TrackLine:
    """One tracks.jsonl line's track; LineError naming `where` otherwise."""
    kind, raw = _one(line, where)
    if kind != TRACK_KEY:
        raise OtherKind(f"{where}: expected a {TRACK_KEY} line, got {kind}")
    try:
        return _track.decode(raw)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise LineError(f"{where}: {kind}: {exc}") from None


def decode_counts(line: bytes | str, where: str = "counts.jsonl line") -> CountsLine:
    """One counts.jsonl line's interval; LineError naming `where` otherwise."""
    kind, raw = _one(line, where)
    if kind != COUNTS_KEY:
        raise OtherKind(f"{where}: expected a {COUNTS_KEY} line, got {kind}")
    try:
        return _counts.decode(raw)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise LineError(f"{where}: {kind}: {exc}") from None


def encode_track(item: TrackLine) -> bytes:
    """A tracks.jsonl line's bytes (no newline)."""
    return _json.encode({TRACK_KEY: item})


def encode_counts(item: CountsLine) -> bytes:
    """A counts.jsonl line's bytes (no newline)."""
    return _json.encode({COUNTS_KEY: item})


def doc_rows() -> list[tuple[str, str, str, str, str]]:
    """The results.jsonl table of docs/results.md from the Structs' Meta: (kind, key,
    present, type, meaning) per field in line order, "as above" where a key means what it
    meant for an earlier kind; the plugin row last."""
    rows: list[tuple[str, str, str, str, str]] = []
    said: dict[str, str] = {}
    for kind, cls in KINDS.items():
        for f in msgspec.inspect.type_info(cls).fields:  # type: ignore[attr-defined]
            meta = f.type
            meaning = meta.extra_json_schema["description"]
            shown = "as above" if said.get(f.name) == meaning else meaning
            said.setdefault(f.name, meaning)
            rows.append((kind, f.name, meta.extra["present"], meta.extra["type"], shown))
    rows.append(("*plugin name*", *PLUGIN_DOC))
    return rows
