"""The softhil CAN protocol: the frames, and the DBC file `softhil.dbc` that declares them.

The DBC is the protocol: ids, layouts, scaling, units, physical ranges, value tables, comments
and cycle times (`GenMsgCycleTime`). This module adds no frame knowledge of its own. A DBC
message named `<Kind><index>` (`DriveStatus3`, `CameraMarker0`) or `<Kind>` (`SYNC`) is a frame
of kind `Kind`; a frame type is a frozen, slotted dataclass registered for its kind with
`@frame_type`, whose fields are the message's signals plus, for indexed kinds, the index field
(`node`, `marker_id`). Kinds with no registered type decode to `GenericFrame`. Adding a frame
type is a DBC addition plus, where typed access is wanted, one decorated dataclass next to the
code that uses it. Each message's payload is encoded and decoded by its `rigbus.codec`
`MessageCodec` (a `struct.Struct` made from the DBC when it is loaded).

Frames are ``dataclass(frozen=True, slots=True)``, built by dataclasses' own `__init__`. A
NamedTuple is quicker to build (a DriveStatus by keywords: 6.3 thousand instructions, 0.71 us,
against 12.9 thousand, 1.44 us: a frozen dataclass sets each field through object.__setattr__,
slots or not) and a third slower to read; the dataclass is chosen for what a frame means: equal
only to a frame of its own type (a NamedTuple DriveCommand equals a ControllerState, or a tuple,
with the same values, so every ``decode(m) == frame`` check would be blind to the type), no
tuple behaviour (iteration, indexing, `len`), and the dataclass functions (`replace`, `asdict`,
`fields`) the code, the tests and a user's controller use. Decoded frames are built in C
(`rigbus.ccodec`), which fills their slots directly.

Ids follow CANopen ranges: SYNC 0x080, EMCY 0x080+n, status 0x180+n (valves 0x190+n, canister
0x1A0), command 0x200+n (valves 0x210+n), camera frame 0x27F, markers 0x280+m (3-D 0x290+m),
controller state 0x380+n, heartbeat 0x700+n.

Invariant: every frame on the bus decodes to exactly one frame object, or `decode` raises
`FrameError` naming the CAN id; `encode(decode(m)) == m` for every valid message.
"""

from __future__ import annotations

import functools
import operator
import re
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from importlib.resources import files
from pathlib import Path
from typing import Any, ClassVar

import can
import cantools
from cantools.database.can import Database, Message

from rigbus import ccodec
from rigbus.canbus import c_messages, unchecked_message
from rigbus.codec import COUNTER_MODULO as COUNTER_MODULO
from rigbus.codec import Data, FrameError, MessageCodec, frame_error, frame_name

DBC_PATH = Path(str(files("rigbus") / "softhil.dbc"))

SYNC_ID = 0x080  # the SYNC message's id in the DBC (CANopen's); checked by the tests

EMCY_OVER_PRESSURE = 0xFF01
EMCY_COMMAND_TIMEOUT = 0xFF02
EMCY_FMU_FAULT = 0xFF03
NMT_OPERATIONAL = 5

_NAME = re.compile(r"^(?P<kind>.*?)(?P<index>\d*)$")


@dataclass(frozen=True)
class FrameType:
    """How a dataclass maps onto DBC messages of one kind: `kinds` names each field's type,
    "bool", "int" or "float" (a decoded value becomes bool(int(v)), int(v) or float(v))."""

    kind: str
    cls: type
    index_field: str | None
    kinds: dict[str, str]


_REGISTRY: dict[str, FrameType] = {}
_REGISTERED = [0]  # how many registrations `_REGISTRY` has seen (a Protocol's layout depends on it)


def _to_bool(value: Any) -> bool:
    return bool(int(value))


CONVERTERS: dict[str, Callable[[Any], Any]] = {"bool": _to_bool, "int": int, "float": float}


def frame_type(kind: str, index: str | None = None) -> Callable[[type], type]:
    """Register a frozen dataclass as the typed frame of DBC kind `kind` (its messages are
    `kind` or `kind<N>`); `index` names the field that holds N."""

    def register(cls: type) -> type:
        hints = typing.get_type_hints(cls)
        kinds = {
            f.name: "bool" if hints[f.name] is bool else "int" if hints[f.name] is int else "float"
            for f in fields(cls)
        }
        _REGISTRY[kind] = FrameType(kind, cls, index, kinds)
        _REGISTERED[0] += 1
        cls.kind = kind  # type: ignore[attr-defined]
        return cls

    return register


_UNSEEN: Any = object()  # a frame class `Protocol._entry_of` has not met yet


@dataclass(frozen=True)
class GenericFrame:
    """A frame of a kind with no registered type: its DBC kind, index and signals."""

    kind: str
    index: int | None
    signals: Mapping[str, float] = field(default_factory=dict)


@frame_type("SYNC")
@dataclass(frozen=True, slots=True)
class Sync:
    counter: int


@frame_type("DriveStatus", index="node")
@dataclass(frozen=True, slots=True)
class DriveStatus:
    node: int
    piston_position: float  # [m]
    p_a: float  # [Pa gauge]
    p_b: float  # [Pa gauge]
    fault: int
    counter: int


@frame_type("DriveCommand", index="node")
@dataclass(frozen=True, slots=True)
class DriveCommand:
    node: int
    piston_setpoint: float  # [m]
    enable: bool
    counter: int


@frame_type("ControllerState", index="node")
@dataclass(frozen=True, slots=True)
class ControllerState:
    node: int
    kappa_ref: float  # [1/m]
    kappa_est: float  # [1/m]
    counter: int


@frame_type("TaskState")
@dataclass(frozen=True, slots=True)
class TaskState:
    """The task-space controller's state (recorded by the plant, used to score the task)."""

    target_index: int  # target (point-to-point) or path (path tracking), 0 first
    phase: int  # TASK_PHASES
    target_x: float  # [m] the task-space reference point now
    target_y: float  # [m]
    counter: int


@frame_type("SpatialTaskState")
@dataclass(frozen=True, slots=True)
class SpatialTaskState:
    """The spatial arm controller's task state (recorded by the plant, used to score the task)."""

    target_index: int  # goal pursued, 0 first (modulo 256)
    phase: int  # TASK_PHASES
    target_x: float  # [m] the task-space reference point now (world frame)
    target_y: float  # [m]
    target_z: float  # [m]


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
@dataclass(frozen=True, slots=True)
class Emcy:
    node: int
    error_code: int
    error_register: int
    pressure: float  # [Pa gauge]
    counter: int


@frame_type("Heartbeat", index="node")
@dataclass(frozen=True, slots=True)
class Heartbeat:
    node: int
    nmt_state: int


@frame_type("CameraMarker", index="marker_id")
@dataclass(frozen=True, slots=True)
class CameraMarker:
    marker_id: int
    x: float  # [m]
    y: float  # [m]
    frame_index: int
    exposure_offset: float  # SYNC time - exposure time [s]


@frame_type("CameraMarker3D", index="marker_id")
@dataclass(frozen=True, slots=True)
class CameraMarker3D:
    marker_id: int
    frame_index: int
    x: float  # [m]
    y: float  # [m]
    z: float  # [m]


@frame_type("CameraFrame")
@dataclass(frozen=True, slots=True)
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


@functools.cache
def _values_of(names: tuple[str, ...]) -> Callable[[Any], tuple[Any, ...]]:
    """A function giving the tuple of a frame's attributes `names` (in C)."""
    if len(names) == 1:
        (name,) = names
        return lambda frame: (getattr(frame, name),)
    return operator.attrgetter(*names)


def _arranger(positions: Sequence[int]) -> Callable[[Sequence[Any]], tuple[Any, ...]]:
    """A function taking a sequence to the tuple of its items at `positions` (in C)."""
    if len(positions) == 1:
        (only,) = positions
        return lambda items: (items[only],)
    if list(positions) == list(range(len(positions))):
        return tuple
    return operator.itemgetter(*positions)  # type: ignore[return-value]


@dataclass(frozen=True)
class _Entry:
    kind: str
    index: int | None
    message: Message
    type: FrameType | None
    codec: MessageCodec


class Protocol:
    """Encoder/decoder of softhil frames over the DBC database (strict range checks)."""

    _cache: ClassVar[dict[Path, Database]] = {}
    # the codecs of the cached databases' messages (which live as long as the cache), by
    # message: a Protocol is made in many places
    _codecs: ClassVar[dict[int, tuple[Message, MessageCodec]]] = {}
    # the entries by id, name and (kind, index) of a DBC's messages, by its path and the frame
    # types registered when they were made: checked once, shared by every Protocol (read only)
    _layouts: ClassVar[dict[tuple[Path, int], tuple[dict, dict, dict]]] = {}

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
        self._by_id: dict[int, _Entry]
        self._by_name: dict[str, _Entry]
        self._by_key: dict[tuple[str, int | None], _Entry]
        self._by_id, self._by_name, self._by_key = self._layout(database, dbc_path)
        # `_entry_of`'s memory: the index field of each typed frame class met, and by (class,
        # int index) the CAN id, values getter and encoders of each typed frame met (`encode`'s
        # first lines): the C codec's plain case and its capsule (`rigbus.ccodec`), then the
        # codec's own `encode`
        self._index_fields: dict[type, str | None] = {}
        self._typed: dict[tuple[type, Any], tuple[int, Callable[[Any], Any], Any, Any, Any]] = {}
        # `decode`'s first lines: by CAN id, the payload's length, the C decoder's plain case
        # and its capsule, then the frame's builder in Python
        self._builders: dict[int, tuple[int, Any, Any, Callable[[Data], Frame]]] = {}
        module = ccodec.load()
        self._pack = _no_c if module is None else module.pack
        self._unpack = _no_c if module is None else module.unpack
        made_in_c = c_messages()  # the message of a frame the C codec packed, made in C too
        self._data_message = data_message if made_in_c is None else made_in_c.data_message

    @staticmethod
    def _layout(database: Database, dbc_path: Path) -> tuple[dict, dict, dict]:
        """The entries of `database`'s messages by CAN id, by name and by (kind, index), each
        registered type checked against its message (FrameError)."""
        key = (dbc_path, _REGISTERED[0])
        known = Protocol._layouts.get(key)
        if known is not None:
            return known
        by_id: dict[int, _Entry] = {}
        by_name: dict[str, _Entry] = {}
        by_key: dict[tuple[str, int | None], _Entry] = {}
        for message in database.messages:
            match = _NAME.match(message.name)
            assert match is not None  # the pattern matches every string
            kind, digits = match["kind"], match["index"]
            ftype = _REGISTRY.get(kind)
            index = int(digits) if digits else None
            entry = _Entry(kind, index, message, ftype, Protocol._codec(message))
            if ftype is not None:
                _check_layout(entry)
            by_id[message.frame_id] = entry
            by_name[message.name] = entry
            by_key[(kind, index)] = entry
        Protocol._layouts[key] = (by_id, by_name, by_key)
        return by_id, by_name, by_key

    @staticmethod
    def _codec(message: Message) -> MessageCodec:
        """The message's codec, made once per message object."""
        cached = Protocol._codecs.get(id(message))
        if cached is not None and cached[0] is message:
            return cached[1]
        codec = MessageCodec(message)
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
        """The DBC message of `frame`; FrameError if it has none."""
        if isinstance(frame, GenericFrame):
            return self._entry(frame.kind, frame.index)
        cls = type(frame)
        ftype = _REGISTRY.get(getattr(cls, "kind", ""))
        if ftype is None or not isinstance(frame, ftype.cls):
            raise FrameError(f"{cls.__name__} is not a registered frame type")
        field = ftype.index_field
        if field is None:
            entry, given = self._entry(ftype.kind, None), None
        else:
            given = getattr(frame, field)
            entry = self._entry(ftype.kind, int(given))
        # remembered for `encode` by class and index as given, if an int: a later index equal
        # to it, such as 3.0 or True, is the index int() makes of it, the same message
        if (field is None or type(given) is int) and (cls, given) not in self._typed:
            self._index_fields[cls] = field
            codec = entry.codec
            capsule = ccodec.encoder(codec) if self._pack is not _no_c else None
            pack = _no_c if capsule is None else self._pack
            frame_id, values_of = entry.message.frame_id, _values_of(codec.names)
            self._typed[(cls, given)] = (frame_id, values_of, pack, capsule, codec.encode)
        return entry

    def _entry(self, kind: str, index: int | None) -> _Entry:
        entry = self._by_key.get((kind, index))
        if entry is None:
            name = kind if index is None else f"{kind}{index}"
            raise FrameError(f"{name}: no such frame in the DBC (index out of range)")
        return entry

    # ------------------------------------------------------------------ encode / decode

    def encode(self, frame: Frame, timestamp: float = 0.0) -> can.Message:
        """The CAN message of `frame`; out-of-range values raise FrameError naming the signal."""
        cls = type(frame)
        field = self._index_fields.get(cls, _UNSEEN)
        if field is not _UNSEEN:  # a typed frame met before: its message at once
            try:
                typed = self._typed.get((cls, None if field is None else getattr(frame, field)))
            except TypeError:  # an unhashable index: `_entry_of` says what is wrong
                typed = None
            if typed is not None:
                frame_id, values_of, pack, capsule, encode = typed
                values = values_of(frame)
                data = pack(capsule, values)  # C's plain case, else None
                return self._data_message(
                    frame_id, encode(values) if data is None else data, timestamp
                )
        entry = self._entry_of(frame)
        codec = entry.codec
        if isinstance(frame, GenericFrame):
            values = codec.values_of(frame.signals)
        else:
            values = _values_of(codec.names)(frame)
        return self._data_message(entry.message.frame_id, codec.encode(values), timestamp)

    def decode(self, msg: can.Message) -> Frame:
        """The frame of a received message; unknown ids and malformed data raise FrameError."""
        known = self._builders.get(msg.arbitration_id)  # an id decoded before
        if known is not None:
            length, unpack, capsule, build = known
            if (
                len(msg.data) == length
                and not msg.is_extended_id
                and not msg.is_error_frame
                and not msg.is_remote_frame
            ):
                frame = unpack(capsule, msg.data)  # C's plain case, else None
                return build(msg.data) if frame is None else frame
        if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            raise FrameError(f"unexpected extended/error/remote frame 0x{msg.arbitration_id:X}")
        entry = self._by_id.get(msg.arbitration_id)
        if entry is None:
            raise FrameError(f"unknown CAN id {frame_name(msg.arbitration_id)}")
        message = entry.message
        if len(msg.data) != message.length:
            raise frame_error(message, f"{len(msg.data)} data bytes, the DBC says {message.length}")
        build = _builder(entry)
        ftype, capsule = entry.type, None
        if ftype is not None and self._unpack is not _no_c:
            capsule = ccodec.decoder(
                entry.codec, ftype.cls, ftype.kinds, ftype.index_field, entry.index
            )
        unpack = _no_c if capsule is None else self._unpack
        self._builders[msg.arbitration_id] = (message.length, unpack, capsule, build)
        return build(msg.data)


def _no_c(capsule: Any, x: Any) -> None:
    """The C codec's call where there is none: never the plain case."""


def _builder(entry: _Entry) -> Callable[[Data], Frame]:
    """The function building the frame of a payload of `entry`'s message: its typed frame
    (each value through its field's converter, the index field from the CAN id) or a
    GenericFrame."""
    codec = entry.codec
    decode, names = codec.decode, codec.names
    if entry.type is None:
        kind, index, as_mapping = entry.kind, entry.index, codec.as_mapping
        return lambda data: GenericFrame(kind, index, as_mapping(decode(data)))
    cls, index_field = entry.type.cls, entry.type.index_field
    # a field's converter where the decoded value is not already of the field's type
    kinds = [entry.type.kinds[name] for name in names]
    if all(
        (kind == "int" and integral) or (kind == "float" and not integral)
        for kind, integral in zip(kinds, codec.integral(), strict=True)
    ):
        convert_all = decode
    else:
        converters_of = tuple(CONVERTERS[kind] for kind in kinds)

        def convert_all(data: Data) -> tuple[Any, ...]:
            return tuple(map(operator.call, converters_of, decode(data)))

    # the frame's fields, positionally: the converted values, then the index from the CAN id
    slots: dict[str | None, int] = {name: k for k, name in enumerate(names)}
    slots[index_field] = len(names)
    positions = [slots[f.name] for f in fields(cls)]
    tail = () if index_field is None else (entry.index,)
    if index_field in names:
        return _checked_builder(entry, convert_all, _arranger(positions), names.index(index_field))
    if positions == list(range(len(names))):  # no index field, signals in field order
        return lambda data: cls(*convert_all(data))
    if positions == [len(names), *range(len(names))]:  # the index field, then the signals
        index = entry.index
        return lambda data: cls(index, *convert_all(data))
    arrange = _arranger(positions)
    return lambda data: cls(*arrange((*convert_all(data), *tail)))


def _checked_builder(
    entry: _Entry,
    convert_all: Callable[[Data], tuple[Any, ...]],
    arrange: Callable[[tuple[Any, ...]], tuple[Any, ...]],
    given: int,
) -> Callable[[Data], Frame]:
    """The builder of a typed frame whose index field is also a signal (at `given`): a payload
    whose signal disagrees with the CAN id is refused."""
    assert entry.type is not None
    cls, index, index_field = entry.type.cls, entry.index, entry.type.index_field

    def build(data: Data) -> Frame:
        values = convert_all(data)
        if values[given] != index:
            raise frame_error(
                entry.message, f"{index_field} {values[given]} does not match the CAN id"
            )
        return cls(*arrange((*values, index)))

    return build


def data_message(arbitration_id: int, data: bytes, timestamp: float) -> can.Message:
    """`can.Message(arbitration_id=..., data=..., is_extended_id=False, timestamp=...)`, every
    field the same, in a third of the time: a classic data frame with an 11-bit id whose data
    the DBC codec made (its length the DBC's), so `can.Message`'s checks have nothing to find."""
    return unchecked_message(
        timestamp, arbitration_id, False, False, False, None, len(data), bytearray(data),
        False, True, False, False,
    )  # fmt: skip


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
