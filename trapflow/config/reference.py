"""The config reference (docs/config.md), generated from the schema itself.

Every key of `trapflow.config.schema.Config` (with the ladder's and the modem's sections) is
a field of a msgspec Struct, documented by the string literal right after it (an attribute
docstring). `render()` reads those from each Struct's source with `ast`, takes the defaults
from a `Config()` instance, and writes one markdown table per section: YAML path, type,
default, doc. A nested Struct is recursed into; a dict or list of Structs (`pools`,
`ladder.levels`) is documented by its value type, under `NAME` or `[]` in the path.

    python -m trapflow.config.reference > docs/config.md

tests/unit/test_config_reference.py keeps docs/config.md equal to `render()`.
"""

from __future__ import annotations

import ast
import inspect
import itertools
import json
import textwrap
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from typing import Any

import msgspec

from trapflow.config.schema import Config

REGENERATE = "python -m trapflow.config.reference > docs/config.md"
_BOUNDS = (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="))


@dataclass(frozen=True)
class Row:
    """One key of the reference."""

    path: str
    type: str
    default: str
    """As markdown, code spans included."""
    doc: str


@cache
def field_docs(cls: type) -> dict[str, str]:
    """A Struct's attribute docstrings by field name, its base classes' included."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not issubclass(klass, msgspec.Struct) or klass.__module__.startswith("msgspec"):
            continue
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        node = tree.body[0]
        assert isinstance(node, ast.ClassDef)
        for field, after in itertools.pairwise(node.body):
            if (isinstance(field, ast.AnnAssign) and isinstance(field.target, ast.Name)
                    and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                    and isinstance(after.value.value, str)):
                docs[field.target.id] = " ".join(after.value.value.split())
    return docs


def _class_doc(cls: type) -> str:
    return " ".join(inspect.cleandoc(cls.__doc__ or "").split())


def _unwrap(tp: Any) -> tuple[Any, list[msgspec.Meta]]:
    """The type inside Annotated[...] and its msgspec constraints."""
    metas: list[msgspec.Meta] = []
    while typing.get_origin(tp) is typing.Annotated:
        tp, *extras = typing.get_args(tp)
        metas += [m for m in extras if isinstance(m, msgspec.Meta)]
    return tp, metas


def _is_struct(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, msgspec.Struct)


def _struct_value(tp: Any) -> tuple[str, type] | None:
    """('dict' or 'list', the Struct) for a dict or list of Structs, else None."""
    tp, _ = _unwrap(tp)
    args = typing.get_args(tp)
    if typing.get_origin(tp) is dict and _is_struct(_unwrap(args[1])[0]):
        return "dict", _unwrap(args[1])[0]
    if typing.get_origin(tp) is list and _is_struct(_unwrap(args[0])[0]):
        return "list", _unwrap(args[0])[0]
    return None


def _number(value: float) -> str:
    """A bound as one text whether it was written 0 or 0.0: typing caches equal Annotated
    types, so which of two equal bounds a field gets depends on import order."""
    return str(int(value)) if float(value).is_integer() else repr(float(value))


def _constraints(metas: list[msgspec.Meta]) -> str:
    parts: list[str] = []
    for meta in metas:
        parts += [f"{sign} {_number(getattr(meta, key))}" for key, sign in _BOUNDS
                  if getattr(meta, key) is not None]
        if meta.min_length is not None or meta.max_length is not None:
            low = meta.min_length or 0
            parts.append(f"length {low}..{meta.max_length}" if meta.max_length is not None
                         else f"length >= {low}")
    return ", ".join(parts)


def type_name(tp: Any) -> str:
    """A type as a reader of the YAML meets it."""
    tp, metas = _unwrap(tp)
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Literal:
        name = " or ".join(str(a) for a in args)
    elif origin in (types.UnionType, typing.Union):
        name = " or ".join("null" if a is type(None) else type_name(a) for a in args)
    elif origin is list:
        name = f"list of {type_name(args[0])}"
    elif origin is dict:
        name = f"map of {type_name(args[0])} to {type_name(args[1])}"
    elif _is_struct(tp):
        name = "mapping"
    elif tp is Any:
        name = "any"
    else:
        name = getattr(tp, "__name__", str(tp))
    bounds = _constraints(metas)
    return f"{name} ({bounds})" if bounds else name


def value_text(value: Any) -> str:
    """A default as YAML would spell it (JSON flow style)."""
    return json.dumps(msgspec.to_builtins(value), separators=(", ", ": "))


def _default(info: msgspec.structs.FieldInfo) -> Any:
    if info.default is not msgspec.NODEFAULT:
        return info.default
    return info.default_factory()


def _entries(value: Any) -> str:
    """The default of a map or list of Structs: its entries' names (a list item's name is
    its first field), or none."""
    names = list(value) if isinstance(value, dict) else [
        getattr(item, msgspec.structs.fields(item)[0].name) for item in value]
    return ", ".join(f"`{name}`" for name in names) if names else "none"


def _rows(cls: type, prefix: str, base: Any, others: list[tuple[str, Any]]) -> Iterator[Row]:
    """Rows of a Struct's fields under `prefix`. `base` holds the defaults (an instance; None
    for a map's or a list's value type: the fields' own defaults); `others` are the entries
    of a default map, (name, instance), whose values that differ are named beside."""
    docs = field_docs(cls)
    for info in msgspec.structs.fields(cls):
        path = f"{prefix}.{info.name}"
        inner, _ = _unwrap(info.type)
        if _is_struct(inner):
            yield from _rows(inner, path, None if base is None else getattr(base, info.name),
                             [(name, getattr(obj, info.name)) for name, obj in others])
            continue
        yield from _field_rows(info, path, docs.get(info.name, ""),
                               None if base is None else getattr(base, info.name),
                               [(name, getattr(obj, info.name)) for name, obj in others])


def _field_rows(info: msgspec.structs.FieldInfo, path: str, doc: str, value: Any,
                others: list[tuple[str, Any]]) -> Iterator[Row]:
    """The row of one key that is not a Struct, then, for a map or list of Structs, the
    rows of its value type."""
    nested = _struct_value(info.type)
    if value is None and info.required:
        default = "required"
    elif nested is not None:  # a map or list of Structs: its entries, by name
        default = _entries(_default(info) if value is None else value)
    else:
        text = value_text(_default(info) if value is None else value)
        differ = [f"{name}: `{_cell(value_text(v))}`" for name, v in others
                  if value_text(v) != text]
        default = f"`{_cell(text)}`" + (f" ({'; '.join(differ)})" if differ else "")
    yield Row(path, type_name(info.type), default, doc)
    if nested is not None:
        kind, struct = nested
        entries = list(value.items()) if kind == "dict" and isinstance(value, dict) else []
        yield from _rows(struct, f"{path}.NAME" if kind == "dict" else f"{path}[]", None,
                         entries)


def sections() -> Iterator[tuple[str, str, list[Row]]]:
    """(title, introduction, rows) per top-level key of the config, from a `Config()`; the
    plain top-level keys come together at the end."""
    config = Config()
    docs = field_docs(Config)
    top: list[Row] = []
    for info in msgspec.structs.fields(Config):
        inner, _ = _unwrap(info.type)
        nested = _struct_value(info.type)
        value = getattr(config, info.name)
        if _is_struct(inner):
            yield info.name, _class_doc(inner), list(_rows(inner, info.name, value, []))
        elif nested is not None:
            rows = list(_field_rows(info, info.name, docs.get(info.name, ""), value, []))
            yield info.name, _class_doc(nested[1]), rows
        else:
            top.extend(_field_rows(info, info.name, docs.get(info.name, ""), value, []))
    yield "Top-level keys", "Keys of the config itself.", top


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def render() -> str:
    """docs/config.md: every key of the config with its type, default and doc."""
    out = [
        "# Config reference",
        "",
        "Every key of the YAML config (`trapflow start --config FILE`), generated from the",
        "field docs of the config's Structs (`trapflow/config/`); regenerate it with",
        f"`{REGENERATE}` (a test keeps it equal to the",
        "schema). A config changes only the keys it gives; a key not listed",
        "here is refused with its path (`$.pools.vo.policy`). `configs/default.yaml` holds",
        "the same defaults as a file to start from. `NAME` in a path is any name of a map (a",
        "pool, a level's pool), `[]` any item of a list. In brackets beside a default: the",
        "entries of the default map that differ from it (the default pools).",
        "",
    ]
    all_sections = list(sections())
    out += [", ".join(f"[{title}](#{title.lower().replace(' ', '-')})"
                      for title, _, _ in all_sections), ""]
    for title, intro, rows in all_sections:
        out += [f"## {title}", "", intro.strip(), "",
                "| key | type | default | what it does |", "|---|---|---|---|"]
        out += [f"| `{r.path}` | {_cell(r.type)} | {r.default} | {_cell(r.doc)} |"
                for r in rows]
        out.append("")
    return "\n".join(out)


if __name__ == "__main__":
    print(render(), end="")
