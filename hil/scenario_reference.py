"""The reference of every scenario key, written from the schema (hil.schema): each section's
keys with their type, unit, range, default and description, the rules between keys, every
robot kind's `[robot]` section and tables, and the FMU parameters a table passes on (from each
model's model.toml). `hil scenarios --keys` prints it; docs/scenario-keys.md is its output,
kept current by a test.

Invariant: nothing here is written by hand per key: a key missing from the reference is a key
missing from the schema.
"""

from __future__ import annotations

import typing
from collections.abc import Iterable, Iterator
from dataclasses import is_dataclass
from typing import Any

from hil.schema import (
    INTERNAL,
    REQUIRED,
    Key,
    Range,
    RobotSection,
    Table,
    bound_text,
    keys_of,
    number,
)
from hil.schema import type_text as _type_text

HEADER = """# Scenario keys

Every key a scenario file can hold, written from the schema by `hil scenarios --keys`
(do not edit: `hil scenarios --keys > docs/scenario-keys.md`). A range is inclusive at `[`
`]`, exclusive at `(` `)`; bounds may be other keys or the DBC. A problem with a key is one
line naming the file, the key, the rule and the value.
"""
COLUMNS = "| key | type | unit | range | default | description |\n|---|---|---|---|---|---|"


def reference(kinds: Iterable[str] | None = None) -> str:
    """The reference, as Markdown, with the robot kinds `kinds` (default: every kind found,
    plug-ins too; docs/scenario-keys.md has the built-in ones)."""
    from hil.rig import known_kinds, robot_kind
    from hil.scenario import Scenario

    parts = [HEADER]
    for path, cls, doc in _sections(Scenario, "", "The scenario's own keys."):
        parts.append(_section(path, cls, doc, _title(path)))
    for kind in known_kinds() if kinds is None else kinds:
        spec = robot_kind(kind).spec_class
        parts.append(_section("robot", spec, _doc(spec), f"[robot] (kind {kind})"))
        for table in getattr(spec, "TABLES", ()):
            parts.append(_table(table, kind))
    return "\n".join(parts)


def _sections(cls: type, path: str, doc: str) -> Iterator[tuple[str, type, str]]:
    """(path, class, what it is) of `cls` and of the sections declared within it, depth
    first; an array of sections is at `path[i]`."""
    yield path, cls, _sentence(_doc(cls) or doc)
    for key in keys_of(cls):
        inner = _inner(key.hint)
        if inner is not None:
            sub = _join(path, key.toml_name)
            array = typing.get_origin(key.hint) is tuple
            yield from _sections(inner, f"{sub}[i]" if array else sub, key.doc)


def _sentence(text: str) -> str:
    return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")


def _inner(hint: Any) -> type | None:
    """The section class a key holds: a section, an optional one, or an array of them."""
    for candidate in (hint, *typing.get_args(hint)):
        if isinstance(candidate, type) and is_dataclass(candidate):
            return candidate
    return None


def _title(path: str) -> str:
    if not path:
        return "Top level"
    if path.endswith("[i]"):
        return f"[[{path.removesuffix('[i]')}]]"
    return f"[{path}]"


def _section(path: str, cls: type, doc: str, title: str) -> str:
    keys = [k for k in keys_of(cls) if k.doc != INTERNAL and k.hint is not RobotSection]
    rows = [_row(k, path) for k in keys if _inner(k.hint) is None]
    lines = [f"## {title}", "", doc, "", COLUMNS, *rows]
    tables = [_join(path, k.toml_name) for k in keys_of(cls) if _inner(k.hint) is not None]
    tables += [_join(path, k.toml_name) for k in keys_of(cls) if k.hint is RobotSection]
    if tables:
        said = ", ".join(f"`{_title(t + ('[i]' if t == 'connections' else ''))}`" for t in tables)
        lines += ["", f"Tables: {said}."]
    lines += _rules(getattr(cls, "RULES", ()))
    return "\n".join(lines) + "\n"


def _doc(cls: type) -> str:
    text = " ".join((cls.__doc__ or "").split())
    return "" if text.startswith(cls.__name__ + "(") else text  # dataclass's generated doc


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _row(key: Key, path: str) -> str:
    cells = [
        f"`{_join(path, key.toml_name)}`",
        _type_text(key.hint),
        key.unit,
        _range(key),
        _default(key.default),
        key.doc,
    ]
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def _range(key: Key) -> str:
    said = []
    if key.choices is not None:
        said.append(key.choices.phrase(None).removeprefix("be "))
    if key.pattern is not None:
        said.append(key.pattern.says)
    if key.range is not None:
        said.append(_notation(key.range, key.integer))
    if key.not_empty is not None:
        said.append("not empty")
    return "; ".join(said)


def _notation(r: Range, integer: bool) -> str:
    """A range as an interval: (0, 1], 1..8, > 0, <= 1 / camera.rate; with its why."""
    lo, hi = (None if b is None else bound_text(b) for b in (r.lo, r.hi))
    if lo is not None and hi is not None:
        if integer and not (r.lo_open or r.hi_open):
            text = f"{lo}..{hi}"
        else:
            text = f"{'(['[not r.lo_open]}{lo}, {hi}{')]'[not r.hi_open]}"
    elif lo is not None:
        text = f"{'>' if r.lo_open else '>='} {lo}"
    else:
        text = f"{'<' if r.hi_open else '<='} {hi}"
    return f"{text} ({r.why})" if r.why else text


def _default(value: Any) -> str:
    if value is REQUIRED:
        return "required"
    if value is None:
        return "(absent)"
    if is_dataclass(value):
        return "(table)"
    return _toml(value)


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return number(value)
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + "}"
    return str(value)


def _rules(rules: Any) -> list[str]:
    if not rules:
        return []
    return ["", "Rules:", "", *(f"- `{rule.key}`: {rule.text()}" for rule in rules)]


def _table(table: Table, kind: str) -> str:
    lines = [f"## {_title(table.path)} (kind {kind})", "", _sentence(table.doc)]
    if table.keys:
        lines += ["", COLUMNS, *(_row(k, table.path) for k in table.keys)]
    lines += _rules(table.rules)
    if table.fmu:
        lines += ["", *_fmu(table)]
    elif table.others:
        lines += ["", f"Its other keys: {table.others}."]
    return "\n".join(lines) + "\n"


def _fmu(table: Table) -> list[str]:
    """The FMU parameters the table passes on: name, unit, range, default, description."""
    from hil.fmu.build import model_folder
    from hil.fmu.spec import load_spec

    spec = load_spec(model_folder(table.fmu))
    parameters = [v for v in spec.variables if v.causality == "parameter"]
    if table.settable:
        parameters = [v for v in parameters if v.name in table.settable]
    parameters = [v for v in parameters if v.name not in table.refused]
    its = "Its other keys are" if table.keys else "Its keys are"
    lines = [f"{its} {table.fmu} parameters (fmus/{table.fmu}/model.toml):", ""]
    if table.refused:
        refused = ", ".join(f"`{name}`" for name in table.refused)
        lines = [f"Not here: {refused} ({table.refused_why}).", "", *lines]
    lines += [
        "| parameter | unit | range | default | description |",
        "|---|---|---|---|---|",
    ]
    return lines + [_parameter(v, table.starts.get(v.name, v.start)) for v in parameters]


def _parameter(v: Any, start: float | None) -> str:
    """An FMU parameter's row (`v`: hil.fmu.spec.Variable) with its default `start`."""
    lo = "-inf" if v.min is None else number(float(v.min))
    hi = "inf" if v.max is None else number(float(v.max))
    cells = [
        f"`{v.name}`",
        "" if v.unit in (None, "1") else str(v.unit),
        f"[{lo}, {hi}]",
        "" if start is None else number(float(start)),
        " ".join(v.description.split()),
    ]
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"
