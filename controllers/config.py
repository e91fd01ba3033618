"""What every robot's controller configuration shares: the camera's timing, the policies, the
estimators, and reading a configuration from JSON with every key and type checked.

A robot kind's controller side (`rigbus.robots`) has its own configuration dataclass (with a
`robot` and a `policy` key) built on these; `read_config` picks it by the JSON's `robot` key.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rigbus.robots import controller_side, known

POLICIES = ("strict", "hold")
ESTIMATORS = ("raw", "kf", "ukf")


@dataclass(frozen=True)
class CameraTiming:
    """When camera frames become available, in macro-step ticks: frame j is exposed at tick
    j * period_ticks, up to delay_ticks later (exposure jitter), and available latency_ticks
    after its exposure; SYNC c is at tick c * control_ticks. A frame is due at the first SYNC by
    which it is available however late its exposure: waiting for it earlier would wait on a
    frame the camera has not taken yet (the count, not the order of arrival, decides)."""

    period_ticks: int
    latency_ticks: int
    control_ticks: int
    markers: int
    delay_ticks: int = 0  # the latest an exposure falls after its nominal tick (jitter)
    dims: int = 2  # 2: planar markers (CameraMarker frames), 3: spatial (CameraMarker3D)

    def __post_init__(self) -> None:
        """ValueError naming the key for timing no camera has (every robot's config)."""
        if min(self.period_ticks, self.control_ticks) < 1 or self.latency_ticks < 0:
            raise ValueError("camera_timing: period_ticks and control_ticks must be at least 1")
        if not 0 <= self.delay_ticks < self.period_ticks:
            raise ValueError(
                f"camera_timing.delay_ticks: {self.delay_ticks} is outside 0..period_ticks - 1"
            )

    def frames_due(self, cycle: int) -> int:
        """How many frames (0, 1, ... j) are available by SYNC `cycle`, however late their
        exposure."""
        tick = cycle * self.control_ticks - self.latency_ticks - self.delay_ticks
        return 0 if tick < 0 else tick // self.period_ticks + 1


def read_config(text: str) -> Any:
    """A controller configuration of any robot kind, by its `robot` key (default planar_arm);
    ValueError naming the key otherwise."""
    data = json.loads(text)
    if not isinstance(data, dict):
        raise ValueError("must be a JSON object")
    robot = data.get("robot", "planar_arm")
    if not isinstance(robot, str):
        raise ValueError(f"robot: must be a string, got {robot!r}")
    if robot not in known():
        raise ValueError(f"robot: {robot!r} is not one of {', '.join(known())}")
    return controller_side(robot).config_class.from_json(text)


def config_from_json(cls: Any, text: str) -> Any:
    """A robot's controller configuration (a dataclass with a `policy`) from its JSON text:
    every key and type checked, ValueError naming the key; the robot checks the rest."""
    data = json.loads(text)
    if not isinstance(data, dict):
        raise ValueError("must be a JSON object")
    config = _from_data(cls, data, "")
    if config.policy not in POLICIES:
        raise ValueError(f"policy: {config.policy!r} is not one of {', '.join(POLICIES)}")
    return config


def _from_data(cls: Any, data: Any, key: str) -> Any:
    """A dataclass from JSON data, checking every key and type (ValueError naming the key)."""
    hints = typing.get_type_hints(cls)
    if not isinstance(data, dict):
        raise ValueError(f"{key or 'config'}: must be an object")
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(known)
    if unknown:
        raise ValueError(f"{key + '.' if key else ''}{sorted(unknown)[0]}: unknown key")
    values = {}
    for name, f in known.items():
        sub = f"{key}.{name}" if key else name
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ValueError(f"{sub}: missing key")
            continue
        values[name] = _value(hints[name], data[name], sub)
    return cls(**values)


def _value(hint: Any, raw: Any, key: str) -> Any:
    """The JSON value `raw` as the type `hint` asks for: an optional, a scalar, a tuple or a
    nested dataclass (ValueError naming `key` otherwise)."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return _optional(hint, raw, key)
    scalar = _SCALARS.get(hint)
    if scalar is not None:
        return scalar(raw, key)
    if origin is tuple:
        return _tuple(hint, raw, key)
    if dataclasses.is_dataclass(hint):
        return _from_data(hint, raw, key)
    raise ValueError(f"{key}: unsupported type {hint}")  # pragma: no cover - schema bug


def _optional(hint: Any, raw: Any, key: str) -> Any:
    """`X | None`: null, or a value of X."""
    args = typing.get_args(hint)
    if raw is None and type(None) in args:
        return None
    return _value(next(a for a in args if a is not type(None)), raw, key)


def _boolean(raw: Any, key: str) -> bool:
    if not isinstance(raw, bool):
        raise ValueError(f"{key}: must be true or false, got {raw!r}")
    return raw


def _integer(raw: Any, key: str) -> int:
    # JSON true and false are not integers, although Python's bool is one
    if isinstance(raw, bool) or not isinstance(raw, int):
        raise ValueError(f"{key}: must be an integer, got {raw!r}")
    return raw


def _number(raw: Any, key: str) -> float:
    """A finite float from a JSON number (an integer too: 1 is 1.0)."""
    if isinstance(raw, bool) or not isinstance(raw, int | float):
        raise ValueError(f"{key}: must be a number, got {raw!r}")
    try:
        value = float(raw)
    except OverflowError:
        raise ValueError(f"{key}: must be finite, got {raw!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"{key}: must be finite, got {raw!r}")
    return value


def _string(raw: Any, key: str) -> str:
    if not isinstance(raw, str):
        raise ValueError(f"{key}: must be a string, got {raw!r}")
    return raw


# the scalar types a configuration holds, by type hint: each checks and converts a JSON value
_SCALARS: dict[Any, Callable[[Any, str], Any]] = {
    bool: _boolean,
    int: _integer,
    float: _number,
    str: _string,
}


def _tuple(hint: Any, raw: Any, key: str) -> tuple[Any, ...]:
    """A JSON list as `tuple[X, ...]` (any length) or `tuple[X, Y, ...]` (that many)."""
    args = typing.get_args(hint)
    if not isinstance(raw, list):
        raise ValueError(f"{key}: must be a list, got {raw!r}")
    if len(args) == 2 and args[1] is Ellipsis:
        return tuple(_value(args[0], v, f"{key}[{i}]") for i, v in enumerate(raw))
    if len(raw) != len(args):
        raise ValueError(f"{key}: must have {len(args)} elements")
    return tuple(
        _value(a, v, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, raw, strict=True))
    )
