"""A small TOML writer: the scenario text a batch's trial runs, with its seed and overrides.

Invariant: `tomllib.loads(dumps_toml(d)) == d` for a parsed scenario (tables, arrays of tables,
inline arrays and tables, strings, numbers, booleans; no dates), floats with every digit.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from typing import Any

from hil.errors import HilError

# a key TOML takes bare; any other is written quoted
BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def dumps_toml(data: Mapping[str, Any]) -> str:
    """TOML text of a parsed scenario (tables, arrays of tables, inline arrays and tables,
    strings, numbers, booleans); `tomllib.loads(dumps_toml(d)) == d`. Floats keep every digit
    (repr), so a trial runs exactly the value it was given."""
    lines: list[str] = []
    _table(data, [], lines)
    return "\n".join(lines).lstrip("\n") + "\n"


def _table(data: Mapping[str, Any], path: list[str], lines: list[str]) -> None:
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    arrays = {k: v for k, v in data.items() if _array_of_tables(v)}
    for key, value in data.items():
        if key not in tables and key not in arrays:
            lines.append(f"{_key(key)} = {_value(value)}")
    for key, value in tables.items():
        lines.extend(["", f"[{'.'.join(_key(p) for p in [*path, key])}]"])
        _table(value, [*path, key], lines)
    for key, items in arrays.items():
        for item in items:  # a sub-table header after [[a]] belongs to that element
            lines.extend(["", f"[[{'.'.join(_key(p) for p in [*path, key])}]]"])
            _table(item, [*path, key], lines)


def _array_of_tables(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def _key(key: str) -> str:
    return key if BARE_KEY.fullmatch(key) else _string(key)


def _string(text: str) -> str:
    # JSON's escapes are TOML's, except that TOML wants DEL escaped too
    return json.dumps(text, ensure_ascii=False).replace("\x7f", "\\u007f")


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return _string(value)
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + " }"
    raise HilError(f"cannot write {value!r} as TOML")  # dates: scenarios hold none
