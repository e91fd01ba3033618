"""Keys, rules and their checking: `Key` (declared on a dataclass field with `setting`, or in
a `Table`), the rules between keys (`Needs`, `Multiple`, `Check`), and `check`, which judges a
built section and the sections within it (the package docstring's order)."""

from __future__ import annotations

import types
import typing
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import MISSING, dataclass, field, fields, replace
from functools import cache
from typing import Any

from hil.schema.conditions import Condition, Given, MinItems, OneOf, Pattern, Range, predicate
from hil.schema.messages import Context, got


class _Required:
    """The default of a key that has none."""

    def __repr__(self) -> str:
        return "required"


REQUIRED: Any = _Required()
INTERNAL = "(internal)"  # the doc of a field that is no key of the file (Scenario.source)


class RobotSection:
    """Marker type of the scenario's [robot] section: its schema is the robot kind's
    `spec_class`, chosen by its `kind` key (default planar_arm)."""


@dataclass(frozen=True)
class Key:
    """One key of a section: what `hil scenarios --keys` shows and what is checked.

    `name`, `hint` (its Python type) and `default` come from the dataclass field where the key
    is one (`setting`); `toml` is its name in the file where Python needs another ("from")."""

    name: str = ""
    hint: Any = None
    default: Any = REQUIRED
    unit: str = ""
    doc: str = ""
    range: Range | None = None
    choices: OneOf | None = None
    pattern: Pattern | None = None
    not_empty: str | None = None  # given, it must not be empty; the text says why
    toml: str = ""

    @property
    def toml_name(self) -> str:
        return self.toml or self.name

    @property
    def integer(self) -> bool:
        return optional(self.hint) is int

    def problem(self, value: Any, ctx: Context, computed: bool) -> str | None:
        """Why `value` is not a value of this key (None if it is): its own checks (`computed`
        False) or its range bounded by other keys (`computed` True)."""
        if value is None:
            return None
        for condition in (self.choices, self.pattern, self.range):
            if condition is None or bool(condition.keys) != computed:
                continue
            if not condition.holds(value, ctx):
                said = condition.phrase(ctx, self.unit, self.integer)
                return f"must {said}, got {got(value)}"
        return None


def setting(
    default: Any = REQUIRED,
    unit: str = "",
    doc: str = "",
    range: Range | None = None,
    *,
    choices: OneOf | Sequence[Any] | Mapping[Any, str] | None = None,
    pattern: Pattern | None = None,
    not_empty: str | None = None,
    toml: str = "",
    hint: Any = None,
    factory: Callable[[], Any] | None = None,
) -> Any:
    """A dataclass field declared as a scenario key (see `Key`); mutable defaults by
    `factory`."""
    if choices is not None and not isinstance(choices, OneOf):
        choices = OneOf(choices if isinstance(choices, Mapping) else tuple(choices))
    key = Key(
        hint=hint,
        unit=unit,
        doc=doc,
        range=range,
        choices=choices,
        pattern=pattern,
        not_empty=not_empty,
        toml=toml,
    )
    metadata = {"key": key}
    if factory is not None:
        return field(default_factory=factory, metadata=metadata)
    if default is REQUIRED:
        return field(metadata=metadata)
    return field(default=default, metadata=metadata)


def keys_of(cls: type) -> tuple[Key, ...]:
    """The keys of a section dataclass, in declaration order (fields without `setting` as
    plain keys)."""
    return _declared(typing.cast(Hashable, cls))


@cache  # a class's declarations never change; reading them costs a load 0.1 s each time
def _declared(cls: Any) -> tuple[Key, ...]:
    hints = typing.get_type_hints(cls)
    found = []
    for f in fields(cls):
        key = f.metadata.get("key", Key())
        default = REQUIRED if f.default is MISSING else f.default
        if f.default_factory is not MISSING:
            default = f.default_factory()
        hint = key.hint or hints[f.name]
        found.append(replace(key, name=f.name, hint=hint, default=default))
    return tuple(found)


def optional(hint: Any) -> Any:
    """T for T | None."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(hint) if a is not type(None)]
        return inner[0] if len(inner) == 1 else hint
    return hint


# ---------------------------------------------------------------------- rules


@dataclass(frozen=True)
class Needs:
    """A rule between keys: `key` must meet `must` when the key `when[0]` meets `when[1]`
    (always, without `when`), unless `unless[0]` meets `unless[1]`."""

    key: str
    must: Condition
    when: tuple[str, Condition] | None = None
    unless: tuple[str, Condition] | None = None
    why: str = ""
    unit: str = ""

    def problem(self, ctx: Context) -> str | None:
        for guard, wanted in ((self.when, True), (self.unless, False)):
            if guard is not None and guard[1].holds(ctx.value(guard[0]), ctx) != wanted:
                return None
        value = ctx.value(self.key)
        absent_ok = not isinstance(self.must, Given | MinItems)  # an absent key: its default
        if (value is None and absent_ok) or self.must.holds(value, ctx):
            return None
        if isinstance(self.must, Given):
            return self.text(ctx)
        said = str(len(value)) if isinstance(self.must, MinItems) else got(value)
        return f"{self.text(ctx)}, got {said}"

    def text(self, ctx: Context | None = None) -> str:
        said = f"must {self.must.phrase(ctx, self.unit)}"
        if self.when is not None:
            said += f" when {self.when[0]} {predicate(self.when[1])}"
        if self.unless is not None:
            said += f" unless {self.unless[0]} {predicate(self.unless[1])}"
        return said + (f" ({self.why})" if self.why else "")


@dataclass(frozen=True)
class Multiple:
    """`key` [s] (its period 1 / key with `as_period`) is an integer multiple of `of` [s];
    zero only with `allow_zero`."""

    key: str
    of: str
    as_period: bool = False
    allow_zero: bool = False

    def problem(self, ctx: Context) -> str | None:
        value, unit = ctx.value(self.key), ctx.value(self.of)
        if value is None or not unit or (self.as_period and not value):
            return None
        period = 1.0 / value if self.as_period else value
        ratio = period / unit
        n = round(ratio)
        if abs(ratio - n) <= 1e-9 * max(1.0, ratio) and (n >= 1 or self.allow_zero):
            return None
        what = f"period {period:g} s" if self.as_period else f"{period:g} s"
        return f"{what} is not an integer multiple of {self.of} = {unit:g} s"

    def text(self, ctx: Context | None = None) -> str:
        what = "have a period (1 / value) that is" if self.as_period else "be"
        zero = ", or 0" if self.allow_zero else ""
        return f"must {what} an integer multiple of {self.of}{zero}"


@dataclass(frozen=True)
class Check:
    """A rule that is code: `fn(value, ctx)` says why the value of `key` is wrong (None if it
    is not); `doc` says what it checks."""

    key: str
    fn: Callable[[Any, Context], str | None]
    doc: str

    def problem(self, ctx: Context) -> str | None:
        value = ctx.value(self.key)
        return None if value is None else self.fn(value, ctx)

    def text(self, ctx: Context | None = None) -> str:
        return self.doc


Rule = Needs | Multiple | Check


# ---------------------------------------------------------------------- tables kept as dicts


@dataclass(frozen=True)
class Table:
    """A table the code keeps as a dict (`[robot.gripper]`): its own keys, its rules, and what
    its other keys are (`others`; "" when it has none)."""

    path: str
    keys: tuple[Key, ...]
    rules: tuple[Rule, ...] = ()
    others: str = ""  # what its other keys are ("" and no `fmu`: it has none)
    doc: str = ""
    skip: tuple[str, ...] = ()  # keys read elsewhere (sub-tables), neither read nor refused
    fmu: str = ""  # its other keys are this FMU's parameters (the reference lists them)
    checked: bool = True  # False: the robot kind's code reads and checks it
    starts: Mapping[str, float] = field(default_factory=dict)  # FMU defaults overridden here
    settable: tuple[str, ...] = ()  # of the FMU's parameters, those it may set (empty: all)
    refused: tuple[str, ...] = ()  # of the FMU's parameters, those it may not set
    refused_why: str = ""  # what the refused ones come from instead
