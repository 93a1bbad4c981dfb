"""The typed lines of trapflow.wire.result_lines are the lines a run writes: every shape the
normalizer's builder makes decodes to its kind's Struct and encodes back to the same bytes
(so moving a reader onto the Structs changes no byte and no schema version); tracks.jsonl
and counts.jsonl lines do the same; a bad line says which line and what was wrong; the
modem codec's per-kind tables carry only fields the Structs define, with values the
Structs accept; and docs/results.md's table is the Structs' own documentation."""

from __future__ import annotations

import pytest

from tests.unit.test_results_schema import DOC, PLUGIN_ROW, SHAPES, _lines
from trapflow.config.schema import ObserveConfig
from trapflow.modem.codec import KINDS as CODEC_KINDS
from trapflow.modem.codec import LinkCodec
from trapflow.normalizer.result_json import dumps, link_record
from trapflow.tracking.stage import Observer
from trapflow.wire import result_lines as rl

# Records only the modem makes (not lines of results.jsonl): their fields are its own.
MODEM_ONLY = {"health", "aggregate", "track", "counts", "new_label", "new_max_n", "thumb"}


def _built() -> list[bytes]:
    return [dumps(obj) for shapes in SHAPES.values() for body in shapes for obj in _lines(body)]


def test_every_line_the_builder_writes_decodes_and_encodes_to_its_own_bytes() -> None:
    lines = _built()
    kinds = set()
    for line in lines:
        got = rl.decode_result(line)
        kinds.add(got.kind)
        assert isinstance(got.item, rl.KINDS.get(got.kind, rl.PluginLine))
        assert got.pool == "p"
        assert rl.encode_result(got.kind, got.item) == line
        assert dumps({got.kind: rl.result_body(got.item)}) == line
    assert kinds == {*rl.KINDS, "sonar"}


def test_lines_of_older_versions_and_without_newline_decode() -> None:
    line = (b'{"mono_ir":{"timestamp":"2026-01-01 00:00:00.000","seq":3,"label":"crab",'
            b'"confidence":0.5,"box":[1.0,2.0,3.0,4.0],"track":null,"v":2}}')
    got = rl.decode_result(line + b"\n")
    assert got.pool is None and got.item.track is None  # type: ignore[union-attr]
    assert rl.encode_result(*got) == line


@pytest.mark.parametrize(("line", "said"), [
    (b'{"mono_ir": {"seq": 1', "expected a JSON object of one kind"),
    (b'{"a": {}, "b": {}}', "got 2 keys (a, b)"),
    (b'{"mono_ir": {"timestamp": "t", "label": "x", "confidence": 1.0, "box": []}}',
     "mono_ir: Object missing required field `seq`"),
    (b'{"stereo_ir": {"timestamp": "t", "seq": "7", "label": "x", "confidence": 1.0}}',
     "stereo_ir: Expected `int`, got `str` - at `$.seq`"),
    (b'{"sonar": {"timestamp": "t"}}', "sonar: Object missing required field `seq`"),
])
def test_a_bad_line_says_which_line_and_what_was_wrong(line: bytes, said: str) -> None:
    with pytest.raises(rl.LineError) as err:
        rl.decode_result(line, "results.jsonl line 12")
    assert str(err.value).startswith("results.jsonl line 12: ")
    assert said in str(err.value)


def _observed() -> tuple[list[bytes], list[bytes]]:
    """tracks.jsonl and counts.jsonl lines as the observation stage writes them: a measured
    crab that stays, an unmeasured fish that passes."""
    obs = Observer(ObserveConfig(interval_s=2.0))
    tracks, counts = [], []
    for i in range(40):
        t_ns = 1_700_000_000_000_000_000 + i * 100_000_000
        items = [{"label": "crab", "confidence": 0.9, "box": [10.0 + i, 10.0, 60.0 + i, 50.0],
                  "xyz": [0.01 * i, 0.0, 1.0], "length_m": 0.1, "length_sd_m": 0.01}]
        if i < 10:
            items.append({"label": "fish", "confidence": 0.8,
                          "box": [300.0, 200.0 + 5 * i, 340.0, 230.0 + 5 * i]})
        got = obs.feed(t_ns, items)
        tracks += got.tracks
        counts += got.counts
    end = obs.finish()
    return ([dumps(t) for t in tracks + end.tracks], [dumps(c) for c in counts + end.counts])


def test_track_and_count_lines_decode_and_encode_to_their_own_bytes() -> None:
    tracks, counts = _observed()
    assert len(tracks) == 2 and counts
    decoded = [rl.decode_track(line) for line in tracks]
    assert {t.label for t in decoded} == {"crab", "fish"}
    assert any(isinstance(t.speed_m_s, float) for t in decoded)  # the measured keys too
    assert [rl.encode_track(t) for t in decoded] == tracks
    assert [rl.encode_counts(rl.decode_counts(line)) for line in counts] == counts
    with pytest.raises(rl.LineError, match="tracks.jsonl line 3: expected a track line"):
        rl.decode_track(counts[0], "tracks.jsonl line 3")


def test_the_modem_codec_carries_only_fields_of_the_structs() -> None:
    """Every field of a result kind's codec table is a field of its Struct, and what the
    codec gives back for it converts to the Struct's type (each codec field is exercised by
    a line of the builder)."""
    assert {key for key, _ in CODEC_KINDS.values()} - set(rl.KINDS) == MODEM_ONLY, (
        "a new record kind of the codec: a result kind gets a Struct here, a record only "
        "the modem makes goes to MODEM_ONLY")
    codec = LinkCodec()
    carried: dict[str, set[str]] = {}
    for line in _built():
        got = rl.decode_result(line)
        if got.kind not in rl.KINDS:
            continue
        back = codec.decode(codec.encode(link_record({got.kind: rl.result_body(got.item)})))
        body = back[got.kind]
        carried.setdefault(got.kind, set()).update(body)
        typed = rl.result_item(got.kind, body)  # LineError when a value does not fit
        assert type(typed) is rl.KINDS[got.kind]
    for key, fields in CODEC_KINDS.values():
        if key in rl.KINDS:
            names = [name for name, _ in fields]
            assert set(names) <= set(rl.KINDS[key].__struct_fields__), key
            assert set(names) <= carried[key], (key, sorted(set(names) - carried[key]))


def test_the_docs_table_is_the_structs_documentation() -> None:
    text = DOC.read_text(encoding="utf-8")
    section = text[text.index("## results.jsonl"):]
    rows = set()
    for row in section.splitlines():
        cells = [c.strip() for c in row.strip().strip("|").split("|")]
        if len(cells) == 5 and cells[1].startswith("`"):
            if cells[0] != PLUGIN_ROW:
                cells[0], cells[1] = cells[0].strip("`"), cells[1].strip("`")
            rows.add(tuple(cells))
    assert rows == set(rl.doc_rows())
