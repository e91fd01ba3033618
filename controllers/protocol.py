"""The softhil CAN protocol: the DBC file `softhil.dbc`, typed frames, encode/decode, bus load.

The DBC file is the protocol (ids, scaling, units, ranges); this module only names its frames.
It lives on the controller side because both programs speak it and `controllers` never imports
`hil`. Ids follow CANopen ranges: SYNC 0x080, EMCY 0x080+n, status 0x180+n, command 0x200+n,
camera markers 0x280+m, controller state 0x380+n, heartbeat 0x700+n (drives n = 1..8).
Invariant: every frame on the bus decodes to exactly one of the dataclasses below, or
`decode` raises `FrameError` naming the CAN id.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import Any

import can
import cantools
from cantools.database.can import Database, Message

DBC_PATH = Path(str(files("controllers") / "softhil.dbc"))

SYNC_ID = 0x080
EMCY_BASE = 0x080
STATUS_BASE = 0x180
COMMAND_BASE = 0x200
MARKER_BASE = 0x280
STATE_BASE = 0x380
HEARTBEAT_BASE = 0x700
MAX_DRIVES = 8
MAX_MARKERS = 16
COUNTER_MODULO = 256

EMCY_OVER_PRESSURE = 0xFF01
EMCY_COMMAND_TIMEOUT = 0xFF02
EMCY_FMU_FAULT = 0xFF03
NMT_OPERATIONAL = 5


class FrameError(ValueError):
    """A frame that cannot be encoded or decoded; the message names the frame and CAN id."""


@dataclass(frozen=True)
class Sync:
    counter: int


@dataclass(frozen=True)
class DriveStatus:
    node: int
    piston_position: float  # [m]
    p_a: float  # [Pa gauge]
    p_b: float  # [Pa gauge]
    fault: int
    counter: int


@dataclass(frozen=True)
class DriveCommand:
    node: int
    piston_setpoint: float  # [m]
    enable: bool
    counter: int


@dataclass(frozen=True)
class ControllerState:
    node: int
    kappa_ref: float  # [1/m]
    kappa_est: float  # [1/m]
    counter: int


@dataclass(frozen=True)
class Emcy:
    node: int
    error_code: int
    error_register: int
    pressure: float  # [Pa gauge]
    counter: int


@dataclass(frozen=True)
class Heartbeat:
    node: int
    nmt_state: int


@dataclass(frozen=True)
class CameraMarker:
    marker_id: int
    x: float  # [m]
    y: float  # [m]
    frame_index: int
    exposure_offset: float  # SYNC time - exposure time [s]


Frame = Sync | DriveStatus | DriveCommand | ControllerState | Emcy | Heartbeat | CameraMarker

# frame class -> (DBC name prefix, id base, name of the field that selects the node/marker)
_LAYOUT: dict[type, tuple[str, int, str | None]] = {
    Sync: ("SYNC", SYNC_ID, None),
    DriveStatus: ("DriveStatus", STATUS_BASE, "node"),
    DriveCommand: ("DriveCommand", COMMAND_BASE, "node"),
    ControllerState: ("ControllerState", STATE_BASE, "node"),
    Emcy: ("EMCY", EMCY_BASE, "node"),
    Heartbeat: ("Heartbeat", HEARTBEAT_BASE, "node"),
    CameraMarker: ("CameraMarker", MARKER_BASE, "marker_id"),
}


def frame_name(frame_id: int) -> str:
    return f"0x{frame_id:03X}"


class Protocol:
    """Encoder/decoder of softhil frames over the DBC database (strict range checks)."""

    def __init__(self, dbc_path: Path = DBC_PATH) -> None:
        database = cantools.database.load_file(str(dbc_path), strict=True)
        if not isinstance(database, Database):
            raise FrameError(f"{dbc_path}: not a CAN database")
        self.database = database
        self._by_id: dict[int, tuple[type, int | None, Message]] = {}
        for cls, (prefix, base, selector) in _LAYOUT.items():
            if selector is None:
                self._by_id[base] = (cls, None, self.database.get_message_by_name(prefix))
                continue
            count = MAX_MARKERS if cls is CameraMarker else MAX_DRIVES
            first = 0 if cls is CameraMarker else 1
            for index in range(first, first + count):
                message = self.database.get_message_by_name(f"{prefix}{index}")
                self._by_id[base + index] = (cls, index, message)

    def message(self, frame_id: int) -> Message:
        return self._by_id[frame_id][2]

    def signal_range(self, message: str, signal: str) -> tuple[float, float]:
        """(minimum, maximum) of a signal as the DBC declares it, in physical units."""
        declared = self.database.get_message_by_name(message).get_signal_by_name(signal)
        if declared.minimum is None or declared.maximum is None:
            raise FrameError(f"{message}.{signal}: the DBC declares no range")
        return float(declared.minimum), float(declared.maximum)

    def frame_id(self, frame: Frame) -> int:
        prefix, base, selector = _LAYOUT[type(frame)]
        index = 0 if selector is None else int(getattr(frame, selector))
        frame_id = base + index
        if frame_id not in self._by_id or (
            selector is not None and self._by_id[frame_id][1] != index
        ):
            raise FrameError(f"{prefix}{index}: no such frame in the DBC (index out of range)")
        return frame_id

    def encode(self, frame: Frame, timestamp: float = 0.0) -> can.Message:
        """The CAN message of `frame`; out-of-range values raise FrameError naming the signal."""
        frame_id = self.frame_id(frame)
        message = self._by_id[frame_id][2]
        signals = {k: v for k, v in vars(frame).items() if k != "node"}
        if isinstance(frame, Sync | DriveStatus | DriveCommand | ControllerState | Emcy):
            signals["counter"] = frame.counter % COUNTER_MODULO
        if isinstance(frame, CameraMarker):
            signals["frame_index"] = frame.frame_index % COUNTER_MODULO
        if isinstance(frame, DriveCommand):
            signals["enable"] = int(frame.enable)
        for name, value in signals.items():
            if isinstance(value, float) and not math.isfinite(value):
                raise FrameError(f"{message.name} ({frame_name(frame_id)}): {name} is {value}")
        try:
            data = message.encode(signals, strict=True)
        except (cantools.database.EncodeError, ValueError, KeyError) as exc:
            raise FrameError(f"{message.name} ({frame_name(frame_id)}): {exc}") from exc
        return can.Message(
            arbitration_id=frame_id, data=data, is_extended_id=False, timestamp=timestamp
        )

    def decode(self, msg: can.Message) -> Frame:
        """The frame of a received message; unknown ids and malformed data raise FrameError."""
        if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            raise FrameError(f"unexpected extended/error/remote frame 0x{msg.arbitration_id:X}")
        entry = self._by_id.get(msg.arbitration_id)
        if entry is None:
            raise FrameError(f"unknown CAN id {frame_name(msg.arbitration_id)}")
        cls, index, message = entry
        if len(msg.data) != message.length:
            raise FrameError(
                f"{message.name} ({frame_name(msg.arbitration_id)}): {len(msg.data)} data bytes, "
                f"the DBC says {message.length}"
            )
        values = message.decode(bytes(msg.data), decode_choices=False, scaling=True)
        fields: dict[str, Any] = dict(values)  # type: ignore[arg-type]
        if cls is CameraMarker:
            if int(fields["marker_id"]) != index:
                raise FrameError(
                    f"{message.name} ({frame_name(msg.arbitration_id)}): marker_id "
                    f"{int(fields['marker_id'])} does not match the CAN id"
                )
            return CameraMarker(
                marker_id=int(fields["marker_id"]),
                x=float(fields["x"]),
                y=float(fields["y"]),
                frame_index=int(fields["frame_index"]),
                exposure_offset=float(fields["exposure_offset"]),
            )
        if cls is Sync:
            return Sync(counter=int(fields["counter"]))
        if cls is DriveCommand:
            return DriveCommand(
                node=int(index or 0),
                piston_setpoint=float(fields["piston_setpoint"]),
                enable=bool(fields["enable"]),
                counter=int(fields["counter"]),
            )
        typed = {k: (int(v) if k in _INTEGER_FIELDS else float(v)) for k, v in fields.items()}
        frame: Frame = cls(node=index, **typed)
        return frame


_INTEGER_FIELDS = {"fault", "counter", "error_code", "error_register", "nmt_state"}


def frame_bits(dlc: int) -> int:
    """Bits on the wire of a classic CAN data frame with an 11-bit id, worst-case bit stuffing:
    44 + 8 dlc frame bits, 3 intermission bits, (34 + 8 dlc - 1) // 4 stuff bits."""
    return 47 + 8 * dlc + (34 + 8 * dlc - 1) // 4


def bus_load(frames_per_second: dict[int, float], bitrate: float, protocol: Protocol) -> float:
    """Fraction of the bus's capacity used by frames at the given rates (by CAN id)."""
    bits = sum(
        rate * frame_bits(protocol.message(frame_id).length)
        for frame_id, rate in frames_per_second.items()
    )
    return bits / bitrate
