"""The schema's messages and the values its checks read: `fail` (the one line), `shown` (a
value as TOML writes it), `got` and `number`, and `Context` (a scenario's keys by dotted path)."""

from __future__ import annotations

import datetime as dt
import functools
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from hil.errors import ScenarioError

if TYPE_CHECKING:
    from rigbus.protocol import Protocol


def fail(file: str, key: str, reason: str) -> ScenarioError:
    """The one-line error of a scenario: file, key, reason."""
    return ScenarioError(f"{file}: {key or '(top level)'}: {reason}")


def shown(value: Any) -> str:
    """A value as TOML writes it, for a message: true, 1.5, 'text', a table, an array, or a
    date or time that needs quotes to be the string it was meant as."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list | tuple):
        return "an array"
    if isinstance(value, dt.datetime):
        text = value.isoformat()
        if value.utcoffset() == dt.timedelta(0):
            text = text.removesuffix("+00:00") + "Z"
        return f"the TOML date-time {text} (quote it)"
    if isinstance(value, dt.date):
        return f"the TOML date {value.isoformat()} (quote it)"
    if isinstance(value, dt.time):
        return f"the TOML time {value.isoformat()} (quote it)"
    return repr(value)


def got(value: Any) -> str:
    """A value that broke a range or a rule, after "got": a number as short as it is exact
    (its type was right), anything else as `shown`."""
    return number(value) if isinstance(value, float) else shown(value)


def number(value: float) -> str:
    """A number as short as it is exact: 0.5, 1e-06, 100, 0.30000000000000004."""
    if isinstance(value, bool) or not isinstance(value, float):
        return str(value)
    text = f"{value:g}"
    return text if float(text) == value else repr(value)


# ---------------------------------------------------------------------- the values of keys


@functools.cache
def _default_protocol() -> Protocol:
    """The protocol over softhil's DBC, made once a process: the checks only read it, and a
    sweep's plan checks every grid point's scenario (5 ms each to make)."""
    from rigbus.protocol import Protocol

    return Protocol()


class Context:
    """What the checks read: the scenario being checked (keys by dotted path), the tables read
    so far, and the protocol (made once, on first use)."""

    def __init__(self, root: Any, file: str) -> None:
        self.root = root
        self.file = file
        self.tables: dict[str, Mapping[str, Any]] = {}
        self._protocol: Protocol | None = None

    @property
    def protocol(self) -> Protocol:
        if self._protocol is None:
            self._protocol = _default_protocol()  # the DBC bounds what the bus can carry
        return self._protocol

    def value(self, path: str) -> Any:
        """The value of the key at `path` ("timing.step", "robot.gripper.theta_open"); None
        where it or a table above it is absent."""
        table, _, name = path.rpartition(".")
        if table in self.tables:
            return self.tables[table].get(name)
        node = self.root
        for part in path.split("."):
            if node is None:
                return None
            node = node.get(part) if isinstance(node, Mapping) else getattr(node, part, None)
        return node
