"""Judging a built scenario: every key's checks and every rule of its sections and tables.

Apart from `hil.schema.keys` (the declarations) and `hil.schema.build` (TOML to sections), which
this module uses both of: a table is read (its keys converted) only when it is checked.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import is_dataclass
from typing import Any

from hil.schema.build import convert
from hil.schema.keys import REQUIRED, Key, RobotSection, Rule, Table, keys_of
from hil.schema.messages import Context, fail


def read_table(self: Table, raw: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
    """The table's own keys converted (defaults filled in), after refusing unknown keys
    where the table has no others; the result is what the rules see at its path."""
    path = self.path
    own = {k.toml_name: k for k in self.keys}
    if not (self.others or self.fmu):
        for name in raw:
            if name not in own and name not in self.skip:
                allowed = ", ".join((*own, *self.skip))
                raise fail(ctx.file, f"{path}.{name}", f"unknown key (allowed: {allowed})")
    values = {}
    for name, key in own.items():
        if name in raw:
            values[name] = convert(key.hint, raw[name], ctx.file, f"{path}.{name}")
        elif key.default is not REQUIRED:
            values[name] = key.default
    ctx.tables[path] = values
    return values


# ---------------------------------------------------------------------- checking sections


def sections(obj: Any, path: str) -> Iterator[tuple[str, Any]]:
    """(path, section) of `obj` and of every section within it, depth first (a tuple of
    sections as `path[i]`); the robot's section is the robot kind's to check."""
    yield path, obj
    for key in keys_of(type(obj)):
        value = getattr(obj, key.name)
        sub = f"{path}.{key.toml_name}" if path else key.toml_name
        if is_dataclass(value) and not isinstance(value, type) and key.hint is not RobotSection:
            yield from sections(value, sub)
        elif isinstance(value, tuple) and value and is_dataclass(value[0]):
            for i, item in enumerate(value):
                yield from sections(item, f"{sub}[{i}]")


def check(obj: Any, path: str, ctx: Context) -> None:
    """Every key's checks and every rule of the section `obj` at `path`, of the sections within
    it and of their tables (`TABLES`, those `checked` and present), in the package docstring's
    order; ScenarioError naming the first failure."""
    found = list(sections(obj, path))
    entries = [
        (f"{p}.{k.toml_name}" if p else k.toml_name, k, getattr(section, k.name))
        for p, section in found
        for k in keys_of(type(section))
    ]
    # a section's rules relate the sections within it: theirs first (deepest first, stably)
    nested = sorted(found, key=lambda item: -_depth(item[0]))
    rules = [rule for _, section in nested for rule in getattr(type(section), "RULES", ())]
    for _, section in found:
        for table in getattr(type(section), "TABLES", ()):
            raw = ctx.value(table.path)
            if table.checked and isinstance(raw, Mapping):
                values = read_table(table, raw, ctx)
                entries += [(f"{table.path}.{k.name}", k, values.get(k.name)) for k in table.keys]
                rules += table.rules
    _check_keys(entries, ctx)
    _check_rules(rules, ctx)


def _depth(path: str) -> int:
    return path.count(".") + bool(path)


def _check_keys(entries: Sequence[tuple[str, Key, Any]], ctx: Context) -> None:
    for computed in (False, True):
        for path, key, value in entries:
            problem = key.problem(value, ctx, computed)
            if problem is not None:
                raise fail(ctx.file, path, problem)


def _check_rules(rules: Sequence[Rule], ctx: Context) -> None:
    for rule in rules:
        problem = rule.problem(ctx)
        if problem is not None:
            raise fail(ctx.file, rule.key, problem)
