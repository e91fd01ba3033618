"""The softhil CAN protocol: one generic codec driven by the DBC file `softhil.dbc`.

The DBC is the protocol: ids, layouts, scaling, units, physical ranges, value tables, comments
and cycle times (`GenMsgCycleTime`). This module adds no frame knowledge of its own. A DBC
message named `<Kind><index>` (`DriveStatus3`, `CameraMarker0`) or `<Kind>` (`SYNC`) is a frame
of kind `Kind`; a frame type is a frozen dataclass registered for its kind with `@frame_type`,
whose fields are the message's signals plus, for indexed kinds, the index field (`node`,
`marker_id`). Kinds with no registered type decode to `GenericFrame`. Adding a frame type is a DBC
addition plus, where typed access is wanted, one decorated dataclass next to the code that uses it.

Ids follow CANopen ranges: SYNC 0x080, EMCY 0x080+n, status 0x180+n (valves 0x190+n, canister
0x1A0), command 0x200+n (valves 0x210+n), camera frame 0x27F, markers 0x280+m (3-D 0x290+m),
controller state 0x380+n, heartbeat 0x700+n.

Invariant: every frame on the bus decodes to exactly one frame object, or `decode` raises
`FrameError` naming the CAN id; `encode(decode(m)) == m` for every valid message.
"""

from __future__ import annotations

import functools
import math
import re
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from importlib.resources import files
from pathlib import Path
from typing import Any, ClassVar

import can
import cantools
from cantools.database.can import Database, Message

from rigbus import ccodec
from rigbus.canbus import c_messages, unchecked_message
from rigbus.records import replace_init

DBC_PATH = Path(str(files("rigbus") / "softhil.dbc"))
Data = bytes | bytearray  # a frame's payload: python-can gives either

SYNC_ID = 0x080  # the SYNC message's id in the DBC (CANopen's); checked by the tests
COUNTER_MODULO = 256
WRAPPING_SIGNALS = ("counter", "frame_index")  # sequence numbers: encoded modulo their range

EMCY_OVER_PRESSURE = 0xFF01
EMCY_COMMAND_TIMEOUT = 0xFF02
EMCY_FMU_FAULT = 0xFF03
NMT_OPERATIONAL = 5

_NAME = re.compile(r"^(?P<kind>.*?)(?P<index>\d*)$")


class FrameError(ValueError):
    """A frame that cannot be encoded or decoded; the message names the frame and CAN id."""


@dataclass(frozen=True)
class FrameType:
    """How a dataclass maps onto DBC messages of one kind."""

    kind: str
    cls: type
    index_field: str | None
    converters: dict[str, Callable[[Any], Any]]


_REGISTRY: dict[str, FrameType] = {}


def _to_bool(value: Any) -> bool:
    return bool(int(value))


def _to_int(value: Any) -> int:
    return int(value)


# the converters as expressions, for the generated decoders (`_Codec.unpacker`)
_CONVERSIONS: dict[Callable[[Any], Any], str] = {
    _to_bool: "bool(int({}))",
    _to_int: "int({})",
    float: "float({})",
}


def frame_type(kind: str, index: str | None = None) -> Callable[[type], type]:
    """Register a frozen dataclass as the typed frame of DBC kind `kind` (its messages are
    `kind` or `kind<N>`); `index` names the field that holds N."""

    def register(cls: type) -> type:
        hints = typing.get_type_hints(cls)
        converters: dict[str, Callable[[Any], Any]] = {}
        for f in fields(cls):
            hint = hints[f.name]
            converters[f.name] = _to_bool if hint is bool else _to_int if hint is int else float
        _REGISTRY[kind] = FrameType(kind, cls, index, converters)
        cls.kind = kind  # type: ignore[attr-defined]
        _fast_init(cls)
        return cls

    return register


def _fast_init(cls: type) -> None:
    """A frame class's quicker `__init__` (`rigbus.records`): some fifty frames are built
    a SYNC. A class that has it is remembered in `_PLAIN`."""
    if replace_init(cls):
        _PLAIN.add(cls)


# the frame classes `_fast_init` handled: an instance is its fields in its dict, nothing more,
# so the C decoder may build one as cls.__new__(cls) and a dict (`_Codec.unpacker`)
_PLAIN: set[type] = set()
_UNSEEN: Any = object()  # a frame class `Protocol._entry_of` has not met yet


@dataclass(frozen=True)
class GenericFrame:
    """A frame of a kind with no registered type: its DBC kind, index and signals."""

    kind: str
    index: int | None
    signals: Mapping[str, float] = field(default_factory=dict)


@frame_type("SYNC")
@dataclass(frozen=True)
class Sync:
    counter: int


@frame_type("DriveStatus", index="node")
@dataclass(frozen=True)
class DriveStatus:
    node: int
    piston_position: float  # [m]
    p_a: float  # [Pa gauge]
    p_b: float  # [Pa gauge]
    fault: int
    counter: int


@frame_type("DriveCommand", index="node")
@dataclass(frozen=True)
class DriveCommand:
    node: int
    piston_setpoint: float  # [m]
    enable: bool
    counter: int


@frame_type("ControllerState", index="node")
@dataclass(frozen=True)
class ControllerState:
    node: int
    kappa_ref: float  # [1/m]
    kappa_est: float  # [1/m]
    counter: int


@frame_type("TaskState")
@dataclass(frozen=True)
class TaskState:
    """The task-space controller's state (recorded by the plant, used to score the task)."""

    target_index: int  # target (point-to-point) or path (path tracking), 0 first
    phase: int  # TASK_PHASES
    target_x: float  # [m] the task-space reference point now
    target_y: float  # [m]
    counter: int


TASK_PHASES = (  # the DBC's values
    "idle",
    "moving",
    "settling",
    "settled",
    "done",
    "tracking",
    "grasping",
    "releasing",
)


@frame_type("EMCY", index="node")
@dataclass(frozen=True)
class Emcy:
    node: int
    error_code: int
    error_register: int
    pressure: float  # [Pa gauge]
    counter: int


@frame_type("Heartbeat", index="node")
@dataclass(frozen=True)
class Heartbeat:
    node: int
    nmt_state: int


@frame_type("CameraMarker", index="marker_id")
@dataclass(frozen=True)
class CameraMarker:
    marker_id: int
    x: float  # [m]
    y: float  # [m]
    frame_index: int
    exposure_offset: float  # SYNC time - exposure time [s]


@frame_type("CameraMarker3D", index="marker_id")
@dataclass(frozen=True)
class CameraMarker3D:
    marker_id: int
    frame_index: int
    x: float  # [m]
    y: float  # [m]
    z: float  # [m]


@frame_type("CameraFrame")
@dataclass(frozen=True)
class CameraFrame:
    frame_index: int
    exposure_offset: float  # SYNC time - exposure time [s]
    marker_mask: int  # bit m: marker m was seen
    markers: int


Frame = Any  # any registered frame dataclass or GenericFrame


def frame_key(frame: Frame) -> tuple[str, int | None]:
    """(DBC kind, index) of a frame object: ("DriveStatus", 3), ("SYNC", None)."""
    if isinstance(frame, GenericFrame):
        return frame.kind, frame.index
    ftype = _REGISTRY[type(frame).kind]
    return ftype.kind, None if ftype.index_field is None else int(getattr(frame, ftype.index_field))


def frame_signals(frame: Frame) -> dict[str, Any]:
    """The signal values of a frame object, by DBC signal name."""
    if isinstance(frame, GenericFrame):
        return dict(frame.signals)
    names = _SIGNAL_FIELDS.get(type(frame))
    if names is None:
        ftype = _REGISTRY[type(frame).kind]
        names = tuple(f.name for f in fields(frame) if f.name != ftype.index_field)
        _SIGNAL_FIELDS[type(frame)] = names
    return {name: getattr(frame, name) for name in names}


_SIGNAL_FIELDS: dict[type, tuple[str, ...]] = {}  # a frame type's signal fields, in field order


def frame_name(frame_id: int) -> str:
    return f"0x{frame_id:03X}"


def _frame_error(message: Message, text: str) -> FrameError:
    """A FrameError that names the message and its CAN id, then says `text`."""
    return FrameError(f"{message.name} ({frame_name(message.frame_id)}): {text}")


class _Codec:
    """One message's encode/decode, compiled from its DBC layout: plain integer arithmetic on the
    little-endian payload, the same rounding and range checks as cantools (strict), several
    times faster. Checked byte for byte against cantools for every message (tests).

    `encode` and `decode` are generated per message (straight-line code, the layout's constants
    bound by name): the same arithmetic, in the same order, as a loop over the signals would do,
    without the loop's unpacking and lookups. `pack` is `encode` preceded by the checks
    `Protocol.encode` makes of a frame's values (missing, bool, wrapping sequence number,
    non-finite), and `unpacker(ftype, index)` is `decode` followed by the construction of the
    typed frame (converters and index field), both generated on first use: a frame goes from
    object to bytes and back in one call each."""

    def __init__(self, message: Message) -> None:
        self.message = message
        self.length = message.length
        self.signals = []
        for s in message.signals:
            if s.byte_order != "little_endian" or s.is_float or s.is_multiplexer:
                raise ValueError(f"{message.name}.{s.name}: layout not compiled")
            identity = s.scale == 1 and s.offset == 0 and isinstance(s.scale, int)
            self.signals.append(
                (
                    s.name,
                    s.start,
                    (1 << s.length) - 1,
                    s.length,
                    s.is_signed,
                    s.scale,
                    s.offset,
                    identity,
                    -math.inf if s.minimum is None else s.minimum,
                    math.inf if s.maximum is None else s.maximum,
                )
            )
        # the range cantools enforces (strict): the declared one widened by a millionth of the
        # scale, and none for a value whose raw value the signal names (its choices)
        self.limits = [
            (
                -math.inf if s.minimum is None else s.minimum - abs(s.conversion.scale) * 1e-6,
                math.inf if s.maximum is None else s.maximum + abs(s.conversion.scale) * 1e-6,
                frozenset(s.choices) if s.choices else None,
                s.conversion.numeric_scaled_to_raw,
            )
            for s in message.signals
        ]
        self.plan = _plan(message)
        self.encode: Callable[[Mapping[str, Any]], bytes] = self._compile_encode()
        self.decode: Callable[[Data], dict[str, Any]] = self._compile_decode()
        self._pack: Callable[[Mapping[str, Any]], bytes] | None = None
        self._unpackers: dict[tuple[type, int | None], Callable[[Data], Any]] = {}
        # the C codec's compiled plans (`rigbus.ccodec`), once made: for the tests
        self.c_encoder: Any = None
        self.c_decoders: dict[tuple[type, int | None], Any] = {}

    @property
    def pack(self) -> Callable[[Mapping[str, Any]], bytes]:
        """`encode` with `Protocol.encode`'s checks of a frame's values first: the plain case
        in C where it is available (`rigbus.ccodec`), everything else in Python."""
        if self._pack is None:
            self._pack = self._with_c_encoder(lambda: self._compile_encode(checked=True))
        return self._pack

    def unpacker(self, ftype: FrameType, index: int | None) -> Callable[[Data], Any]:
        """`decode` into the frame type `ftype` of index `index`, as `Protocol.decode` builds it
        (the plain case in C where it is available)."""
        key = (ftype.cls, index)
        unpack = self._unpackers.get(key)
        if unpack is None:
            python = functools.partial(self._compile_unpack, ftype, index)
            unpack = self._unpackers[key] = self._with_c_decoder(python, ftype, index)
        return unpack

    def _c_layout(self) -> bool:
        """Whether the C codec handles this layout: up to 8 bytes, signals within 64 bits, a
        non-zero scale."""
        return self.length <= 8 and all(
            start + length <= 64 and scale != 0
            for _, start, _, length, _, scale, *_ in self.signals
        )

    def _with_c_encoder(
        self, make: Callable[[], Callable[[Mapping[str, Any]], bytes]]
    ) -> Callable[[Mapping[str, Any]], bytes]:
        """The checked encoder `make` compiles, behind the C encoder's plain case if there is
        one; then compiled when first needed (most frames never need it)."""
        module = ccodec.load()
        if module is None or not self._c_layout():
            return make()
        plan = tuple(
            (name, start, mask, identity, scale, type(offset) is int and offset == 0, offset)
            + (low, high, modulus or 0)
            for (name, start, mask, _, _, scale, offset, identity, _, _), (low, high, _, _), (
                _,
                modulus,
            ) in zip(self.signals, self.limits, self.plan, strict=True)
        )
        try:
            capsule = self.c_encoder = module.compile_encoder(self.length, plan)
        except (ValueError, TypeError, OverflowError):
            return make()
        return _c_first(module.pack, capsule, make)

    def _with_c_decoder(
        self, make: Callable[[], Callable[[Data], Any]], ftype: FrameType, index: int | None
    ) -> Callable[[Data], Any]:
        """The unpacker `make` compiles, behind the C decoder's plain case if there is one (a
        frame class `_fast_init` handled, converters float, int and bool, every signal a
        field); then compiled when first needed."""
        module = ccodec.load()
        names = [f.name for f in fields(ftype.cls)]
        kinds = {float: 0, _to_int: 1, _to_bool: 2}
        if (
            module is None
            or not self._c_layout()
            or ftype.cls not in _PLAIN
            or any(s[0] not in names or ftype.converters[s[0]] not in kinds for s in self.signals)
        ):
            return make()
        position = -1 if ftype.index_field is None else names.index(ftype.index_field)
        plan = tuple(
            (start, mask, length, signed, identity, scale, offset)
            + (kinds[ftype.converters[name]], names.index(name))
            for name, start, mask, length, signed, scale, offset, identity, _, _ in self.signals
        )
        try:
            capsule = module.compile_decoder(
                self.length, ftype.cls, tuple(names), index, position, plan
            )
        except (ValueError, TypeError, OverflowError):
            return make()
        self.c_decoders[(ftype.cls, index)] = capsule
        return _c_first(module.unpack, capsule, make)

    def _missing(self, name: str) -> FrameError:
        return _frame_error(self.message, f"no value for signal {name}")

    def _not_finite(self, name: str, value: float) -> FrameError:
        return _frame_error(self.message, f"{name} is {value}")

    def _index_mismatch(self, field: str | None, value: Any) -> FrameError:
        return _frame_error(self.message, f"{field} {value} does not match the CAN id")

    def _range_error(self, name: str, value: float, lo: float, hi: float) -> FrameError:
        side = f"greater than or equal to {lo}" if value < lo else f"smaller than or equal to {hi}"
        return _frame_error(
            self.message,
            f'Expected signal "{name}" value {side} in message "{self.message.name}", '
            f"but got {value}.",
        )

    def _compile_encode(self, checked: bool = False) -> Callable[[Mapping[str, Any]], bytes]:
        """The message's encoder: straight-line code over its signals. Unchecked, each value is
        range-checked (`limits`) and packed in the DBC's order, as cantools does. `checked`
        first makes `Protocol.encode`'s checks of every value (missing, bool, wrapping counter,
        finite), then the range checks, as the uncompiled path does (its checks, then
        cantools'); a float in range, the common value, passes both with one comparison."""
        space: dict[str, Any] = {"_error": self._range_error, "_round": round, "_divmod": divmod}
        space.update({"_missing": self._missing, "_not_finite": self._not_finite})
        space.update({"_INFINITE": (math.inf, -math.inf), "_float": float, "_ABSENT": object()})
        lines = ["def encode(values):", "    bits = 0"]
        if checked:
            lines.append("    outside = False")
        outside = []  # per signal: the test that its value v is out of range, and the error
        for k, (name, _, _, _, _, scale, offset, _, lo, hi) in enumerate(self.signals):
            low, high, choices, to_raw = self.limits[k]
            space.update({f"N{k}": name, f"MIN{k}": lo, f"MAX{k}": hi, f"LO{k}": low})
            space.update({f"HI{k}": high, f"S{k}": scale, f"O{k}": offset})
            test = f"not LO{k} <= {{v}} <= HI{k}"
            if choices is not None:
                space.update({f"CH{k}": choices, f"RAW{k}": to_raw})
                test += f" and RAW{k}({{v}}) not in CH{k}"
            outside.append((test, f"_error(N{k}, {{v}}, MIN{k}, MAX{k})"))
            if not checked:
                continue
            modulus = self.plan[k][1]
            lines += [
                f"    v{k} = values.get(N{k}, _ABSENT)",
                f"    if v{k} is _ABSENT:",
                f"        raise _missing(N{k})",
                f"    if type(v{k}) is _float:",
                f"        if not LO{k} <= v{k} <= HI{k}:",
                f"            if v{k} != v{k} or v{k} in _INFINITE:",
                f"                raise _not_finite(N{k}, v{k})",
                "            outside = True",
                "    else:",
                f"        if isinstance(v{k}, bool):",
                f"            v{k} = int(v{k})",
            ]
            if modulus is not None:
                lines += [f"        elif isinstance(v{k}, int):", f"            v{k} %= {modulus}"]
            lines += [
                f"        elif v{k} != v{k} or v{k} in _INFINITE:",
                f"            raise _not_finite(N{k}, v{k})",
                f"        if not LO{k} <= v{k} <= HI{k}:",
                "            outside = True",
            ]
        if checked:
            lines.append("    if outside:")
            for k, (test, error) in enumerate(outside):
                v = f"v{k}"
                lines.append(f"        if {test.format(v=v)}:")
                lines.append(f"            raise {error.format(v=v)}")
        for k, (_, start, mask, _, _, _, offset, identity, _, _) in enumerate(self.signals):
            if checked:
                value = f"v{k}"
            else:
                value = "value"
                test, error = outside[k]
                lines += [
                    f"    value = values[N{k}]",
                    f"    if {test.format(v=value)}:",
                    f"        raise {error.format(v=value)}",
                ]
            if identity:
                lines.append(f"    raw = _round({value})")
            else:
                # value - 0 is value exactly (-0.0 included), so a zero offset is not subtracted
                zero = type(offset) is int and offset == 0
                lines += [
                    f"    shifted = {value}" + ("" if zero else f" - O{k}"),
                    f"    quotient, remainder = _divmod(shifted, S{k})",
                    f"    raw = _round(quotient if remainder == 0 else shifted / S{k})",
                ]
            lines.append(f"    bits |= (raw & {mask}) << {start}")
        lines.append(f"    return bits.to_bytes({self.length}, 'little')")
        exec("\n".join(lines), space)  # noqa: S102 - code built above from the DBC's integers
        return space["encode"]  # type: ignore[no-any-return]

    def _compile_decode(self) -> Callable[[Data], dict[str, Any]]:
        space: dict[str, Any] = {"_from_bytes": int.from_bytes}
        lines = ["def decode(data):", "    bits = _from_bytes(data, 'little')", "    values = {}"]
        for k, (name, start, mask, length, signed, scale, offset, identity, _, _) in enumerate(
            self.signals
        ):
            space.update({f"N{k}": name, f"S{k}": scale, f"O{k}": offset})
            lines.append(f"    raw = (bits >> {start}) & {mask}")
            if signed:
                lines += [f"    if raw >> {length - 1}:", f"        raw -= {1 << length}"]
            lines.append(f"    values[N{k}] = " + ("raw" if identity else f"raw * S{k} + O{k}"))
        lines.append("    return values")
        exec("\n".join(lines), space)  # noqa: S102 - code built above from the DBC's integers
        return space["decode"]  # type: ignore[no-any-return]

    def _compile_unpack(self, ftype: FrameType, index: int | None) -> Callable[[Data], Any]:
        """`decode` then the typed frame: each value through its field's converter (bool(int(v)),
        int(v) or float(v)), the index field from the CAN id (a signal of that name must match
        it), as keyword arguments."""
        space: dict[str, Any] = {"_from_bytes": int.from_bytes, "_cls": ftype.cls}
        space["_mismatch"] = functools.partial(self._index_mismatch, ftype.index_field)
        space["_INDEX"] = index
        lines = ["def unpack(data):", "    bits = _from_bytes(data, 'little')"]
        arguments = []
        for k, (name, start, mask, length, signed, scale, offset, identity, _, _) in enumerate(
            self.signals
        ):
            space.update({f"S{k}": scale, f"O{k}": offset})
            lines.append(f"    raw = (bits >> {start}) & {mask}")
            if signed:
                lines += [f"    if raw >> {length - 1}:", f"        raw -= {1 << length}"]
            value = "raw" if identity else f"raw * S{k} + O{k}"
            convert = ftype.converters[name]
            kind = _CONVERSIONS.get(convert)
            if kind is None:  # a converter made elsewhere: called by name
                space[f"C{k}"] = convert
                lines.append(f"    v{k} = C{k}({value})")
            else:
                lines.append(f"    v{k} = {kind.format(value)}")
            arguments.append(f"{name}=v{k}")
        if ftype.index_field is not None:
            position = next(
                (k for k, s in enumerate(self.signals) if s[0] == ftype.index_field), None
            )
            if position is None:
                arguments.append(f"{ftype.index_field}=_INDEX")
            else:
                lines += [f"    if v{position} != _INDEX:", f"        raise _mismatch(v{position})"]
                arguments[position] = f"{ftype.index_field}=_INDEX"
        lines.append(f"    return _cls({', '.join(arguments)})")
        exec("\n".join(lines), space)  # noqa: S102 - code built above from the DBC's integers
        return space["unpack"]  # type: ignore[no-any-return]


def _c_first(
    c_call: Callable[[Any, Any], Any], capsule: Any, make: Callable[[], Callable[[Any], Any]]
) -> Callable[[Any], Any]:
    """`c_call(capsule, x)` (C codec's pack or unpack), or where it returns None (not the plain
    case) the Python codec's function that `make` compiles on that first need."""
    python: Callable[[Any], Any] | None = None

    def call(x: Any) -> Any:
        nonlocal python
        out = c_call(capsule, x)
        if out is None:
            if python is None:
                python = make()
            return python(x)
        return out

    call.parts = (c_call, capsule, call)  # type: ignore[attr-defined]  # `_parts`
    return call


def _no_c(capsule: Any, x: Any) -> None:
    """The C half of `_parts` for a function without one: never the plain case."""


def _parts(function: Callable[[Any], Any]) -> tuple[Callable[[Any, Any], Any], Any, Callable]:
    """(C call, capsule, function) of a `_c_first` function, so that a caller calls C directly
    and `function` only where C returns None; (a C call that always returns None, None,
    function) for a Python-only one."""
    return getattr(function, "parts", (_no_c, None, function))


@dataclass(frozen=True)
class _Entry:
    kind: str
    index: int | None
    message: Message
    type: FrameType | None
    codec: _Codec | None
    # (signal name, modulus of a wrapping sequence number or None), in the DBC's signal order
    plan: tuple[tuple[str, int | None], ...] = ()


class Protocol:
    """Encoder/decoder of softhil frames over the DBC database (strict range checks)."""

    _cache: ClassVar[dict[Path, Database]] = {}
    # compiled codecs by message, for the cached databases' messages (which live as long as
    # the cache): compiling costs ~0.6 ms a message, a Protocol is made in many places
    _codecs: ClassVar[dict[int, tuple[Message, _Codec | None]]] = {}

    def __init__(self, dbc_path: Path = DBC_PATH) -> None:
        try:
            database = Protocol._cache.get(dbc_path) or cantools.database.load_file(
                str(dbc_path), strict=True
            )
        except (OSError, cantools.database.UnsupportedDatabaseFormatError, ValueError) as exc:
            raise FrameError(f"{dbc_path}: not a readable DBC: {_first_line(exc)}") from None
        if not isinstance(database, Database):
            raise FrameError(f"{dbc_path}: not a CAN database")
        Protocol._cache[dbc_path] = database
        self.database = database
        self.path = dbc_path
        self._by_id: dict[int, _Entry] = {}
        self._by_name: dict[str, _Entry] = {}
        self._by_key: dict[tuple[str, int | None], _Entry] = {}
        # by CAN id: the encoders' `_parts`, and for the typed frames decoded before, the
        # payload's length and their generated decoders' `_parts` (`decode`'s first lines)
        self._packs: dict[int, tuple[Callable[[Any, Any], Any], Any, Callable[[Any], Any]]] = {}
        self._fast: dict[int, tuple[int, Callable[[Any, Any], Any], Any, Callable[[Any], Any]]] = {}
        # `_entry_of`'s memory: the index field of each typed frame class met, and the entry
        # of each (class, int index) met
        self._index_fields: dict[type, str | None] = {}
        self._typed: dict[tuple[type, Any], _Entry] = {}
        # `encode`'s first lines: by the same (class, index) keys, a typed frame's CAN id and
        # its encoder's `_parts`, for the frames encoded before whose message has a codec
        self._encoders: dict[tuple[type, Any], tuple[int, Any, Any, Callable[[Any], Any]]] = {}
        made_in_c = c_messages()  # the message of a frame the C codec packed, made in C too
        self._data_message = data_message if made_in_c is None else made_in_c.data_message
        for message in database.messages:
            match = _NAME.match(message.name)
            assert match is not None  # the pattern matches every string
            kind, digits = match["kind"], match["index"]
            ftype = _REGISTRY.get(kind)
            index = int(digits) if digits else None
            codec = Protocol._compiled(message)
            entry = _Entry(kind, index, message, ftype, codec, _plan(message))
            if ftype is not None:
                _check_layout(entry)
            self._by_id[message.frame_id] = entry
            self._by_name[message.name] = entry
            self._by_key[(kind, index)] = entry

    @staticmethod
    def _compiled(message: Message) -> _Codec | None:
        """The message's compiled codec (None: a layout the compiler does not handle, cantools
        does it), compiled once per message object."""
        cached = Protocol._codecs.get(id(message))
        if cached is not None and cached[0] is message:
            return cached[1]
        try:
            codec: _Codec | None = _Codec(message)
        except ValueError:
            codec = None
        Protocol._codecs[id(message)] = (message, codec)
        return codec

    # ------------------------------------------------------------------ the DBC as data

    def message(self, frame_id: int) -> Message:
        return self._by_id[frame_id].message

    def message_by_name(self, name: str) -> Message:
        try:
            return self._by_name[name].message
        except KeyError:
            raise FrameError(f"no message {name!r} in {self.path.name}") from None

    def has_message(self, name: str) -> bool:
        return name in self._by_name

    def signal_range(self, message: str, signal: str) -> tuple[float, float]:
        """(minimum, maximum) of a signal as the DBC declares it, in physical units."""
        declared = self.message_by_name(message).get_signal_by_name(signal)
        if declared.minimum is None or declared.maximum is None:
            raise FrameError(f"{message}.{signal}: the DBC declares no range")
        return float(declared.minimum), float(declared.maximum)

    def cycle_time(self, name: str) -> float | None:
        """The message's `GenMsgCycleTime` [s], None for event-driven messages."""
        cycle = self.message_by_name(name).cycle_time
        return cycle / 1000.0 if cycle else None

    def count(self, kind: str) -> int:
        """How many indexed messages of `kind` the DBC declares (drives, markers, valves)."""
        return sum(1 for e in self._by_id.values() if e.kind == kind and e.index is not None)

    def frame_id(self, frame: Frame) -> int:
        return self._entry_of(frame).message.frame_id

    def name_of(self, frame: Frame) -> str:
        return self._entry_of(frame).message.name

    def _entry_of(self, frame: Frame) -> _Entry:
        # a typed frame met before, by its class and its index as given (an int index: a value
        # equal to it, such as 3.0 or True, is the index int() makes of it, the same entry)
        cls = type(frame)
        field = self._index_fields.get(cls, _UNSEEN)
        if field is not _UNSEEN:
            try:
                entry = self._typed.get((cls, None if field is None else getattr(frame, field)))
            except TypeError:  # an unhashable index: the checks below say what is wrong
                entry = None
            if entry is not None:
                return entry
        remember: tuple[str | None, Any] | None = None  # (index field, index as given)
        if isinstance(frame, GenericFrame):
            kind, index = frame.kind, frame.index
        else:
            ftype = _REGISTRY.get(getattr(cls, "kind", ""))
            if ftype is None or not isinstance(frame, ftype.cls):
                raise FrameError(f"{cls.__name__} is not a registered frame type")
            kind, field = ftype.kind, ftype.index_field
            if field is None:
                index, remember = None, (None, None)
            else:
                given = getattr(frame, field)
                index = int(given)
                remember = (field, given) if type(given) is int else None
        entry = self._by_key.get((kind, index))
        if entry is None:
            name = kind if index is None else f"{kind}{index}"
            raise FrameError(f"{name}: no such frame in the DBC (index out of range)")
        if remember is not None:
            self._index_fields[cls] = remember[0]
            self._typed[(cls, remember[1])] = entry
        return entry

    # ------------------------------------------------------------------ encode / decode

    def encode(self, frame: Frame, timestamp: float = 0.0) -> can.Message:
        """The CAN message of `frame`; out-of-range values raise FrameError naming the signal."""
        cls = type(frame)
        field = self._index_fields.get(cls, _UNSEEN)
        if field is not _UNSEEN:  # a typed frame met before: its encoder at once
            try:
                fast = self._encoders.get((cls, None if field is None else getattr(frame, field)))
            except TypeError:  # an unhashable index: `_entry_of` says what is wrong
                fast = None
            if fast is not None:
                frame_id, c_pack, capsule, pack = fast
                given = frame.__dict__
                data = c_pack(capsule, given)
                return self._data_message(
                    frame_id, pack(given) if data is None else data, timestamp
                )
        entry = self._entry_of(frame)
        message = entry.message
        given = frame.signals if isinstance(frame, GenericFrame) else frame.__dict__
        if entry.codec is not None:  # the checks below and the encoding, in one call
            parts = self._packs.get(message.frame_id)
            if parts is None:
                parts = self._packs[message.frame_id] = _parts(entry.codec.pack)
            field = self._index_fields.get(cls, _UNSEEN)
            if field is not _UNSEEN:  # `_entry_of` remembered this class and index
                key = (cls, None if field is None else getattr(frame, field))
                if self._typed.get(key) is entry:
                    self._encoders[key] = (message.frame_id, *parts)
            c_pack, capsule, pack = parts  # the C codec's plain case called directly
            data = c_pack(capsule, given)
            return self._data_message(
                message.frame_id, pack(given) if data is None else data, timestamp
            )
        signals: dict[str, Any] = {}
        for name, modulus in entry.plan:
            if name not in given:
                raise _frame_error(message, f"no value for signal {name}")
            value = given[name]
            if isinstance(value, bool):
                value = int(value)
            elif modulus is not None and isinstance(value, int):
                value %= modulus
            elif value != value or value in (math.inf, -math.inf):  # NaN or infinite
                raise _frame_error(message, f"{name} is {value}")
            signals[name] = value
        try:
            data = message.encode(signals, strict=True)
        except (cantools.database.EncodeError, ValueError, KeyError) as exc:
            raise _frame_error(message, str(exc)) from exc
        return can.Message(
            arbitration_id=message.frame_id, data=data, is_extended_id=False, timestamp=timestamp
        )

    def decode(self, msg: can.Message) -> Frame:
        """The frame of a received message; unknown ids and malformed data raise FrameError."""
        fast = self._fast.get(msg.arbitration_id)  # a typed frame's id decoded before
        if fast is not None:
            length, c_unpack, capsule, unpack = fast
            if (
                len(msg.data) == length
                and not msg.is_extended_id
                and not msg.is_error_frame
                and not msg.is_remote_frame
            ):
                frame = c_unpack(capsule, msg.data)
                return unpack(msg.data) if frame is None else frame
        if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            raise FrameError(f"unexpected extended/error/remote frame 0x{msg.arbitration_id:X}")
        entry = self._by_id.get(msg.arbitration_id)
        if entry is None:
            raise FrameError(f"unknown CAN id {frame_name(msg.arbitration_id)}")
        message = entry.message
        if len(msg.data) != message.length:
            raise _frame_error(
                message, f"{len(msg.data)} data bytes, the DBC says {message.length}"
            )
        ftype = entry.type
        if entry.codec is not None:
            if ftype is not None:  # decoded and built in one call, from now on (`_fast`)
                unpack = entry.codec.unpacker(ftype, entry.index)
                self._fast[msg.arbitration_id] = (message.length, *_parts(unpack))
                return unpack(msg.data)
            values = entry.codec.decode(msg.data)
        else:
            values = dict(
                message.decode(bytes(msg.data), decode_choices=False, scaling=True)  # type: ignore[arg-type]
            )
        if ftype is None:
            return GenericFrame(entry.kind, entry.index, values)
        kwargs = {name: ftype.converters[name](v) for name, v in values.items()}
        if ftype.index_field is not None:
            if ftype.index_field in kwargs and kwargs[ftype.index_field] != entry.index:
                raise _frame_error(
                    message,
                    f"{ftype.index_field} {kwargs[ftype.index_field]} does not match the CAN id",
                )
            kwargs[ftype.index_field] = entry.index
        return ftype.cls(**kwargs)


def data_message(arbitration_id: int, data: bytes, timestamp: float) -> can.Message:
    """`can.Message(arbitration_id=..., data=..., is_extended_id=False, timestamp=...)`, every
    field the same, in a third of the time: a classic data frame with an 11-bit id whose data
    the DBC codec made (its length the DBC's), so `can.Message`'s checks have nothing to find."""
    return unchecked_message(
        timestamp, arbitration_id, False, False, False, None, len(data), bytearray(data),
        False, True, False, False,
    )  # fmt: skip


def _plan(message: Message) -> tuple[tuple[str, int | None], ...]:
    """(signal name, modulus of a wrapping sequence number or None), in the DBC's order."""
    return tuple(
        (
            signal.name,
            int(signal.maximum or COUNTER_MODULO - 1) + 1
            if signal.name in WRAPPING_SIGNALS
            else None,
        )
        for signal in message.signals
    )


def _check_layout(entry: _Entry) -> None:
    """A registered type's fields must be exactly the DBC message's signals (plus the index)."""
    assert entry.type is not None
    wanted = {s.name for s in entry.message.signals}
    if entry.type.index_field is not None:
        wanted.add(entry.type.index_field)
    have = {f.name for f in fields(entry.type.cls)}
    if wanted != have:
        raise FrameError(
            f"{entry.message.name}: the DBC's signals {sorted(wanted)} do not match "
            f"{entry.type.cls.__name__}'s fields {sorted(have)}"
        )


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def frame_bits(dlc: int) -> int:
    """Bits on the wire of a classic CAN data frame with an 11-bit id, worst-case bit stuffing:
    44 + 8 dlc frame bits, 3 intermission bits, (34 + 8 dlc - 1) // 4 stuff bits."""
    return 47 + 8 * dlc + (34 + 8 * dlc - 1) // 4


def bus_load(frames_per_second: Mapping[str, float], bitrate: float, protocol: Protocol) -> float:
    """Fraction of the bus's capacity used by frames at the given rates (by DBC message name)."""
    bits = sum(
        rate * frame_bits(protocol.message_by_name(name).length)
        for name, rate in frames_per_second.items()
    )
    return bits / bitrate
