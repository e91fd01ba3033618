"""Building sections from parsed TOML: `build` (unknown keys, required keys) and `convert`
(each value to its field's type), with one-line errors; and `type_text`, a type as the
reference shows it."""

from __future__ import annotations

import math
import types
import typing
from collections.abc import Callable
from dataclasses import is_dataclass
from typing import Any

from hil.schema.keys import INTERNAL, REQUIRED, RobotSection, keys_of, optional
from hil.schema.messages import fail, shown


def build(cls: type, data: Any, file: str, key: str) -> Any:
    """The section `cls` from the parsed table `data` at `key`: unknown keys refused (listing
    the allowed), each value converted to its field's type, required keys present."""
    if not isinstance(data, dict):
        raise fail(file, key, f"must be a table, got {shown(data)}")
    declared = {k.toml_name: k for k in keys_of(cls)}
    values: dict[str, Any] = {}
    for raw_name, raw in data.items():
        sub = f"{key}.{raw_name}" if key else raw_name
        if raw_name not in declared:
            allowed = ", ".join(n for n, k in declared.items() if k.doc != INTERNAL)
            raise fail(file, sub, f"unknown key (allowed: {allowed})")
        declared_key = declared[raw_name]
        if declared_key.doc == INTERNAL:
            raise fail(file, sub, "unknown key (the file's own path is implied)")
        if raw == [] and declared_key.not_empty is not None:
            why = f" ({declared_key.not_empty})" if declared_key.not_empty else ""
            raise fail(file, sub, f"must not be empty{why}")
        values[declared_key.name] = convert(declared_key.hint, raw, file, sub)
    for k in declared.values():  # the robot's section is there even when the file has none
        if k.hint is RobotSection and k.name not in values:
            values[k.name] = convert(RobotSection, {}, file, k.toml_name)
    for name, k in declared.items():
        if k.name not in values and k.default is REQUIRED:
            raise fail(file, f"{key}.{name}" if key else name, "missing required key")
    return cls(**values)


def convert(hint: Any, raw: Any, file: str, key: str) -> Any:
    """`raw` (parsed TOML) as a value of the type `hint`, or the one-line error."""
    hint = optional(hint)
    if hint is RobotSection:
        return _robot_section(raw, file, key)
    if hint is Any:
        return raw
    scalar = _SCALARS.get(hint)
    if scalar is not None:
        return scalar(raw, file, key)
    origin = typing.get_origin(hint)
    if origin is tuple:
        return _tuple(typing.get_args(hint), raw, file, key)
    if origin is dict:
        if not isinstance(raw, dict):
            raise fail(file, key, f"must be a table, got {shown(raw)}")
        item = typing.get_args(hint)[1]
        return {k: convert(item, v, file, f"{key}.{k}") for k, v in raw.items()}
    if is_dataclass(hint):
        return build(hint, raw, file, key)  # type: ignore[arg-type]
    raise fail(file, key, f"unsupported type {hint}")  # pragma: no cover - schema bug


def _boolean(raw: Any, file: str, key: str) -> bool:
    if not isinstance(raw, bool):
        raise fail(file, key, f"must be true or false, got {shown(raw)}")
    return raw


def _float(raw: Any, file: str, key: str) -> float:
    if isinstance(raw, bool) or not isinstance(raw, int | float):
        raise fail(file, key, f"must be a number, got {shown(raw)}")
    try:
        value = float(raw)
    except OverflowError:
        raise fail(file, key, "must be finite, got a number too large") from None
    if not math.isfinite(value):
        raise fail(file, key, f"must be finite, got {shown(raw)}")
    return value


def _integer(raw: Any, file: str, key: str) -> int:
    if isinstance(raw, bool) or not isinstance(raw, int):
        raise fail(file, key, f"must be an integer, got {shown(raw)}")
    return raw


def _string(raw: Any, file: str, key: str) -> str:
    if not isinstance(raw, str):
        raise fail(file, key, f"must be a string, got {shown(raw)}")
    return raw


_SCALARS: dict[Any, Callable[[Any, str, str], Any]] = {
    bool: _boolean,
    float: _float,
    int: _integer,
    str: _string,
}


def _tuple(args: tuple[Any, ...], raw: Any, file: str, key: str) -> tuple[Any, ...]:
    if not isinstance(raw, list):
        raise fail(file, key, f"must be an array, got {shown(raw)}")
    if len(args) == 2 and args[1] is Ellipsis:
        return tuple(convert(args[0], item, file, f"{key}[{i}]") for i, item in enumerate(raw))
    if len(raw) != len(args):
        raise fail(file, key, f"must have {len(args)} elements, got {len(raw)}")
    return tuple(
        convert(a, item, file, f"{key}[{i}]")
        for i, (a, item) in enumerate(zip(args, raw, strict=True))
    )


def _robot_section(raw: Any, file: str, key: str) -> Any:
    from hil.errors import HilError
    from hil.rig import robot_kind

    if not isinstance(raw, dict):
        raise fail(file, key, f"must be a table, got {shown(raw)}")
    kind = raw.get("kind", "planar_arm")
    if not isinstance(kind, str):
        raise fail(file, f"{key}.kind", f"must be a string, got {shown(kind)}")
    try:
        robot = robot_kind(kind)
    except HilError as exc:
        raise fail(file, f"{key}.kind", str(exc)) from None
    return build(robot.spec_class, raw, file, key)


def type_text(hint: Any) -> str:
    """A key's type as the reference shows it: number, integer, [number, number], table."""
    inner = optional(hint)
    if inner is not hint:
        return f"{type_text(inner)} (optional)"
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return " or ".join(type_text(a) for a in typing.get_args(hint))
    names = {bool: "boolean", float: "number", int: "integer", str: "string", Any: "any"}
    if hint in names:
        return names[hint]
    if typing.get_origin(hint) is tuple:
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"array of {type_text(args[0])}"
        return "[" + ", ".join(type_text(a) for a in args) + "]"
    if typing.get_origin(hint) is dict or is_dataclass(hint) or hint is RobotSection:
        return "table"
    return str(hint)  # pragma: no cover - a type no key has
