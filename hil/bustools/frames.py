"""What the bus tools share: the DBC, frame filters, candump-style text, opening a bus spec.

A filter selects a frame if it matches any `--id` value (`0x181`, `181`: hex, as candump),
any id range (`0x180-0x18F`, both ends included) or any `--message` name glob (`DriveStatus*`);
no filter selects every frame.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass, field
from typing import Any

import can
from cantools.database.can import Database, Message

from hil.errors import BusError, HilError
from rigbus.canbus import BusOpenError, BusSpec, open_bus
from rigbus.protocol import Protocol


def parse_id(text: str) -> int:
    """A CAN id written in hex, with or without 0x."""
    digits = text.strip().lower().removeprefix("0x")
    try:
        value = int(digits, 16)
    except ValueError:
        raise HilError(f"CAN id {text!r}: not a hex number (e.g. 0x181)") from None
    if not 0 <= value <= 0x1FFFFFFF:
        raise HilError(f"CAN id {text!r}: out of range 0x0-0x1FFFFFFF")
    return value


@dataclass(frozen=True)
class FrameFilter:
    ids: frozenset[int] = frozenset()
    ranges: tuple[tuple[int, int], ...] = ()
    names: tuple[str, ...] = ()
    names_of: dict[int, str] = field(default_factory=dict, compare=False)

    @classmethod
    def parse(cls, ids: list[str], names: list[str], database: Database) -> FrameFilter:
        single: set[int] = set()
        ranges: list[tuple[int, int]] = []
        for text in ids:
            for part in text.split(","):
                low, dash, high = part.partition("-")
                if dash and not (low.strip() and high.strip()):  # "-5", "5-": an open range
                    raise HilError(
                        f"--id {part!r}: a range names both ends (e.g. 0x180-0x1FF); a CAN id "
                        "is not negative"
                    )
                if dash:
                    first, last = parse_id(low), parse_id(high)
                    if first > last:
                        raise HilError(f"id range {part!r}: the first id is above the last")
                    ranges.append((first, last))
                else:
                    single.add(parse_id(part))
        names_of = {m.frame_id: m.name for m in database.messages}
        for pattern in names:
            if not any(fnmatch.fnmatchcase(n, pattern) for n in names_of.values()):
                raise HilError(f"--message {pattern!r}: no message of the DBC matches")
        return cls(frozenset(single), tuple(ranges), tuple(names), names_of)

    def __bool__(self) -> bool:
        return bool(self.ids or self.ranges or self.names)

    def matches(self, msg: can.Message) -> bool:
        if not self:
            return True
        frame_id = msg.arbitration_id
        if frame_id in self.ids:
            return True
        if any(first <= frame_id <= last for first, last in self.ranges):
            return True
        name = self.names_of.get(frame_id) if not msg.is_extended_id else None
        return name is not None and any(fnmatch.fnmatchcase(name, p) for p in self.names)


def candump_text(msg: can.Message, channel: str = "can0", direction: bool = True) -> str:
    """The message as one candump -L line (what `.log` files hold), with the R/T flag unless
    `direction` is False (a log that does not record it)."""
    frame_id = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    if msg.is_remote_frame:
        payload = f"R{msg.dlc}" if msg.dlc else "R"
    else:
        payload = bytes(msg.data).hex().upper()
    flag = (" R" if msg.is_rx else " T") if direction else ""
    return f"({msg.timestamp:.6f}) {channel} {frame_id}#{payload}{flag}"


def dbc_message(database: Database, msg: can.Message) -> Message | None:
    """The DBC message of a frame, or None for unknown ids, extended ids and remote frames."""
    if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
        return None
    try:
        return database.get_message_by_frame_id(msg.arbitration_id)
    except KeyError:
        return None


def counter_of(database: Database, msg: can.Message) -> int | None:
    """The SYNC counter a frame carries (its `counter` signal), or None."""
    message = dbc_message(database, msg)
    if message is None or len(msg.data) != message.length:
        return None
    if not any(s.name == "counter" for s in message.signals):
        return None
    return int(decoded(message, msg)["counter"])


def decoded(message: Message, msg: can.Message) -> dict[str, Any]:
    """The signal values of a frame in physical units (numbers, no choice names)."""
    return dict(message.decode(bytes(msg.data), decode_choices=False))  # type: ignore[arg-type]


def load_database() -> Database:
    return Protocol().database


def open_spec(text: str, flag: str | None = "--bus") -> can.BusABC:
    """Open a bus from a spec string (given as option `flag`, if any); a bad spec or a bus
    that will not open is one line."""
    named = f"{flag}: " if flag else ""
    if not text.strip():
        raise BusError(f"{named}empty bus spec; give one, e.g. loopback or socketcan:vcan0")
    try:
        spec = BusSpec.parse(text)
    except ValueError as exc:
        raise BusError(f"{named}{exc}") from None
    try:
        return open_bus(spec)
    except BusOpenError as exc:
        raise BusError(str(exc)) from exc
