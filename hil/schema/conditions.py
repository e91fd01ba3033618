"""Bounds and conditions of the schema: `Range` (with bounds that are numbers, other keys
`Ref`, the DBC `Dbc`, or `Computed`), `OneOf`, `Is`, `Given`, `MinItems` and `Pattern`.

Each condition says itself after "must " (`phrase`: "be in (0, 1] s", "not be negative") and,
said of another key, as a predicate ("is positive"); with a `Context` its bounds are values,
without one (the reference) they are as declared."""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from hil.schema.messages import Context, number, shown


@dataclass(frozen=True)
class Ref:
    """Another key's value times `scale` (or `scale` divided by it, with `per`)."""

    key: str
    scale: float = 1.0
    per: bool = False

    @property
    def keys(self) -> tuple[str, ...]:
        return (self.key,)

    def value(self, ctx: Context) -> float | None:
        value = ctx.value(self.key)
        if value is None or (self.per and value == 0):
            return None
        return self.scale / value if self.per else self.scale * value

    def text(self) -> str:
        if self.per:
            return f"{number(self.scale)} / {self.key}"
        return self.key if self.scale == 1 else f"{number(self.scale)} x {self.key}"


@dataclass(frozen=True)
class Dbc:
    """The DBC's maximum of a signal (`signal` given), or its count of indexed frames of a
    kind (`signal` empty), times `scale`."""

    frame: str
    signal: str = ""
    scale: float = 1.0

    keys: ClassVar[tuple[str, ...]] = ()

    def value(self, ctx: Context) -> float:
        if not self.signal:
            return self.scale * ctx.protocol.count(self.frame)
        return self.scale * ctx.protocol.signal_range(self.frame, self.signal)[1]

    def text(self) -> str:
        if not self.signal:
            return f"{self.frame} frames in the DBC"
        return f"the DBC's {self.frame}.{self.signal} range"


@dataclass(frozen=True)
class Computed:
    """A bound computed from the keys `keys` (and the DBC), said as `text`."""

    says: str
    fn: Callable[[Context], float | None]
    keys: tuple[str, ...] = ()

    def value(self, ctx: Context) -> float | None:
        return self.fn(ctx)

    def text(self) -> str:
        return self.says


Bound = float | int | Ref | Dbc | Computed | None


def _value(bound: Bound, ctx: Context) -> float | None:
    if bound is None or isinstance(bound, int | float):
        return bound
    return bound.value(ctx)


def _shown(value: float | None) -> str:
    return "?" if value is None else number(value)


def bound_text(bound: Bound) -> str:
    """A bound as declared: 0.5, 2 x timing.control_period, the DBC's DriveStatus1.p_a range."""
    if bound is None or isinstance(bound, int | float):
        return number(bound) if bound is not None else "none"
    return bound.text()


# ---------------------------------------------------------------------- conditions


@dataclass(frozen=True)
class Range:
    """lo <= value <= hi (< with `lo_open`, `hi_open`); a bound None is no bound. `why` says
    where the bounds come from."""

    lo: Bound = None
    hi: Bound = None
    lo_open: bool = False
    hi_open: bool = False
    why: str = ""

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(k for b in (self.lo, self.hi) for k in getattr(b, "keys", ()))

    def holds(self, value: Any, ctx: Context) -> bool:
        if value is None:
            return False
        lo, hi = _value(self.lo, ctx), _value(self.hi, ctx)
        low = lo is None or value > lo or (value == lo and not self.lo_open)
        return low and (hi is None or value < hi or (value == hi and not self.hi_open))

    def phrase(self, ctx: Context | None, unit: str = "", integer: bool = False) -> str:
        """What a value must be, after "must ": "be in (0, 1] s", "not be negative"; bounds
        as values (with `ctx`) or as declared (without, for the reference: then a unit follows
        only numbers)."""
        bounds = [b for b in (self.lo, self.hi) if b is not None]
        numeric = ctx is not None or all(isinstance(b, int | float) for b in bounds)
        core = self._core(ctx, f" {unit}" if unit and numeric else "", integer)
        note = self.why
        if not note and ctx is not None:  # a computed bound says what it is
            computed = [b for b in bounds if not isinstance(b, int | float)]
            note = ", ".join(f"{b.text()} = {_shown(_value(b, ctx))}" for b in computed)
        return f"{core} ({note})" if note else core

    def _core(self, ctx: Context | None, u: str, integer: bool) -> str:
        def show(bound: Bound) -> str:
            return bound_text(bound) if ctx is None else _shown(_value(bound, ctx))

        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None:
            if integer and not (self.lo_open or self.hi_open):
                return f"be {show(lo)}..{show(hi)}{u}"
            left, right = "(["[not self.lo_open], ")]"[not self.hi_open]
            return f"be in {left}{show(lo)}, {show(hi)}{right}{u}"
        if lo is not None and isinstance(lo, int | float) and lo == 0:
            return "be positive" if self.lo_open else "not be negative"
        if lo is not None:
            return f"be {'above' if self.lo_open else 'at least'} {show(lo)}{u}"
        if hi is not None:
            return f"be {'below' if self.hi_open else 'at most'} {show(hi)}{u}"
        return "be a number"


def positive(why: str = "") -> Range:
    return Range(0, lo_open=True, why=why)


def not_negative(why: str = "") -> Range:
    return Range(0, why=why)


def fraction() -> Range:
    """A share or probability: 0..1."""
    return Range(0, 1)


@dataclass(frozen=True)
class OneOf:
    """One of `values` (a mapping: each value with what it means); `summary` says them in the
    reference where the list depends on the installation (python-can's interfaces)."""

    values: tuple[Any, ...] | Mapping[Any, str]
    summary: str = ""

    keys: ClassVar[tuple[str, ...]] = ()

    def holds(self, value: Any, ctx: Context) -> bool:
        return value in self.values

    def phrase(self, ctx: Context | None, unit: str = "", integer: bool = False) -> str:
        if ctx is None and self.summary:
            return f"be one of {self.summary}"
        if isinstance(self.values, Mapping):
            return "be one of " + ", ".join(
                f"{shown(v)} ({what})" for v, what in self.values.items()
            )
        return "be one of " + ", ".join(v if isinstance(v, str) else shown(v) for v in self.values)


@dataclass(frozen=True)
class Is:
    """Equal to `value`."""

    value: Any

    keys: ClassVar[tuple[str, ...]] = ()

    def holds(self, value: Any, ctx: Context) -> bool:
        return bool(value == self.value)

    def phrase(self, ctx: Context | None, unit: str = "", integer: bool = False) -> str:
        return f"be {shown(self.value)}"


@dataclass(frozen=True)
class Given:
    """Present and not empty (an empty table counts with `empty`); with `present` False,
    absent or empty ("left out")."""

    present: bool = True
    empty: bool = False

    keys: ClassVar[tuple[str, ...]] = ()

    def holds(self, value: Any, ctx: Context) -> bool:
        empty = isinstance(value, Sequence | Mapping) and not value and not self.empty
        return (value is not None and not empty) == self.present

    def phrase(self, ctx: Context | None, unit: str = "", integer: bool = False) -> str:
        return "be given" if self.present else "be left out"


@dataclass(frozen=True)
class MinItems:
    """At least `count` items, each a `noun`."""

    count: int
    noun: str = "item"

    keys: ClassVar[tuple[str, ...]] = ()

    def holds(self, value: Any, ctx: Context) -> bool:
        return value is not None and len(value) >= self.count

    def phrase(self, ctx: Context | None, unit: str = "", integer: bool = False) -> str:
        return f"have at least {self.count} {self.noun}s"


Condition = Range | OneOf | Is | Given | MinItems


def predicate(condition: Condition) -> str:
    """A condition said of another key: "is positive", "has at least 2 points"."""
    phrase = condition.phrase(None)
    for verb, said in (("not be ", "is not "), ("be ", "is "), ("have ", "has ")):
        if phrase.startswith(verb):
            return said + phrase[len(verb) :]
    return phrase


@dataclass(frozen=True)
class Pattern:
    """A string of the form `regex`, said as `says` ("use letters, digits, ...")."""

    regex: str
    says: str

    keys: ClassVar[tuple[str, ...]] = ()

    def holds(self, value: str, ctx: Context | None = None) -> bool:
        return re.fullmatch(self.regex, value) is not None

    def phrase(self, ctx: Context | None, unit: str = "", integer: bool = False) -> str:
        return self.says
