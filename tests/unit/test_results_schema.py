"""The results.jsonl table of docs/results.md and the result_json writer agree, key by key.

Regression (issue 15): docs/plugins.md described VO lines as `rotation`/`translation` while
results.jsonl writes `Rt`, and no document listed `calib`, `model` or `v`. Every body type a
Result can carry is normalized in each of its shapes (nothing seen, something seen, VO ok
and not); the keys it writes must be exactly the table's, and a key the table says is
"always" there must be in every line of that kind.
"""

from __future__ import annotations

import json
import re
import typing
from pathlib import Path

import pytest

from trapflow.config.schema import ObserveConfig
from trapflow.normalizer.result_json import normalize
from trapflow.tracking.stage import Observer
from trapflow.wire import messages

DOC = Path(__file__).resolve().parents[2] / "docs" / "results.md"
PLUGIN_ROW = "*plugin name*"

ROT = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
POSE = (1.0, 0.0, 0.0, 0.1, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.5)
CORNERS = [(1.0, 2.0), (11.0, 2.0), (11.0, 12.0), (1.0, 12.0)]

# Every shape of every body type a Result carries, as the pipeline fills them in (workers
# stamp `calib` on stereo results; ONNX pools set `model`).
SHAPES: dict[type, list[messages.Msg]] = {
    messages.MonoIR: [
        messages.MonoIR(detections=[messages.Detection("crab", 0.8, (1.0, 2.0, 3.0, 4.0))],
                        model="0123abcd"),
        messages.MonoIR(model="0123abcd"),
        messages.MonoIR(detections=[messages.Detection("crab", 0.8, (1.0, 2.0, 3.0, 4.0))]),
        messages.MonoIR(detections=[messages.Detection(
            "crab", 0.8, (1.0, 2.0, 3.0, 4.0), range_m=1.5, range_sd_m=0.01, xyz=(0, 0, 1.5),
            disparity_px=96.0, length_m=0.2, length_sd_m=0.01, length_method="endpoints")]),
        messages.MonoIR(detections=[messages.Detection("crab", 0.8, (1.0, 2.0, 3.0, 4.0),
                                                       unmeasured="textureless")]),
    ],
    messages.StereoIR: [
        messages.StereoIR(label="crab", confidence=0.7, calib="deadbeef", model="0123abcd"),
        messages.StereoIR(label="none", confidence=0.1, calib="deadbeef"),
    ],
    messages.StereoVO: [
        messages.StereoVO(ok=True, rotation=ROT, translation=(0.1, 0.0, 0.0), pose=POSE,
                          inliers=80, calib="deadbeef"),
        messages.StereoVO(ok=False, pose=POSE, reinit=True, calib="deadbeef"),
        messages.StereoVO(ok=False, calib="deadbeef"),
    ],
    messages.Tags: [
        messages.Tags(tags=[messages.Tag(id=3, corners=CORNERS, rotation=ROT,
                                         translation=(0.0, 0.0, 1.0), error=0.2)],
                      calib="deadbeef"),
        messages.Tags(calib="deadbeef"),
    ],
    messages.Extra: [messages.Extra(name="sonar", fields={"range_m": 1.25})],
}
EXTRA_FIELDS = {"range_m"}  # the plugin's own keys, not the schema's


def _doc_table() -> dict[str, dict[str, str]]:
    """kind -> {key: present} from the results.jsonl table of docs/results.md."""
    text = DOC.read_text(encoding="utf-8")
    start = text.index("## results.jsonl")
    end = text.find("\n## ", start + 1)
    section = text[start:end if end >= 0 else len(text)]
    table: dict[str, dict[str, str]] = {}
    for row in section.splitlines():
        cells = [c.strip() for c in row.strip().strip("|").split("|")]
        if len(cells) != 5 or not cells[1].startswith("`"):
            continue
        kind = cells[0].strip("`")
        for key in re.findall(r"`([^`]+)`", cells[1]):
            table.setdefault(kind, {})[key] = cells[2]
    return table


def _lines(body: messages.Msg) -> list[dict[str, typing.Any]]:
    """The lines as results.jsonl gets them: normalized, then detections tracked (the
    normalizer's observation stage adds `track`)."""
    res = messages.Result(seq=5, t_wall_ns=1_700_000_000_000_000_000, t_mono_ns=1, pool="p",
                          worker="w", proc_ns=1, body=body)  # type: ignore[arg-type]
    objs = normalize(res)
    if isinstance(body, messages.MonoIR):
        Observer(ObserveConfig()).feed(res.t_wall_ns, [o["mono_ir"] for o in objs])
    return objs


def _kind(body: messages.Msg) -> str:
    return PLUGIN_ROW if isinstance(body, messages.Extra) else type(body).__struct_config__.tag


def test_every_result_body_type_has_shapes_here() -> None:
    body = typing.get_type_hints(messages.Result)["body"]
    assert set(typing.get_args(body)) == set(SHAPES), (
        "a new result body type: add its shapes to SHAPES and its keys to docs/results.md")


def test_the_doc_table_lists_every_kind() -> None:
    kinds = {_kind(shapes[0]) for shapes in SHAPES.values()}
    assert set(_doc_table()) == kinds


@pytest.mark.parametrize("body_type", list(SHAPES), ids=lambda t: t.__name__)
def test_normalize_writes_exactly_the_keys_the_doc_documents(body_type: type) -> None:
    table = _doc_table()
    seen: set[str] = set()
    for body in SHAPES[body_type]:
        kind = _kind(body)
        documented = table[kind]
        for obj in _lines(body):
            (name, item), = obj.items()
            assert name == (body.name if isinstance(body, messages.Extra) else kind)
            keys = set(item) - (EXTRA_FIELDS if isinstance(body, messages.Extra) else set())
            seen |= keys
            always = {k for k, present in documented.items() if present == "always"}
            assert always <= keys, f"{kind}: documented as always there but missing: " \
                                   f"{sorted(always - keys)}"
    assert seen == set(documented), (
        f"{kind}: written but not in docs/results.md: {sorted(seen - set(documented))}; "
        f"in docs/results.md but never written: {sorted(set(documented) - seen)}")
    conditional = {k for k, present in documented.items() if present != "always"}
    for key in conditional:  # a condition the shapes exercise: some line lacks the key
        assert any(key not in item for body in SHAPES[body_type]
                   for obj in _lines(body) for item in obj.values()), (kind, key)


def test_the_doc_examples_of_lines_use_the_documented_keys() -> None:
    table = _doc_table()
    text = DOC.read_text(encoding="utf-8")
    examples = [json.loads(block) for block in re.findall(r"```json\n(.*?)\n```", text, re.S)]
    lines = [ex for ex in examples if isinstance(ex, dict) and set(ex) <= set(table)]
    assert lines, "docs/results.md shows no results.jsonl line"
    for ex in lines:
        (kind, item), = ex.items()
        always = {k for k, present in table[kind].items() if present == "always"}
        assert always <= set(item) <= set(table[kind]), (kind, sorted(item))


def test_plugins_doc_points_to_the_results_schema_and_names_rt() -> None:
    """docs/plugins.md describes message bodies; for the file's own keys it defers to the
    table of docs/results.md, and it says VO's rotation and translation are written as `Rt`."""
    doc = (DOC.parent / "plugins.md").read_text(encoding="utf-8")
    assert "(results.md#resultsjsonl)" in doc and "`Rt`" in doc
