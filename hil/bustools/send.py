"""`hil bus send`: one frame in cansend syntax, or one DBC message from signal values.

cansend syntax: `ID#DATA` with ID 3 hex digits (standard, up to 7FF) or 8 (extended, up to
1FFFFFFF), DATA 0..8 bytes in hex, optionally dot-separated (`181#D4.30.00`); `ID#R` or
`ID#R<dlc>` is a remote frame. CAN FD (`ID##...`) is refused. With `--message`, every signal of
the message must be given as `name=value` in physical units and within the DBC's range.

Remote frames go only where the bus can carry them: the loopback hub's socketcand protocol
has no RTR flag (`< send ID LEN DATA >`; socketcand itself drops RTR frames), so python-can's
client would send a 0-byte data frame instead, and softhil's binary records carry data frames
only. `send_one` refuses them there with one line instead of sending something else.
"""

from __future__ import annotations

import re

import can
from can.interfaces.socketcand import SocketCanDaemonBus
from cantools.database.can import Database

from hil.errors import BusError, HilError

_CANSEND = re.compile(r"^(?P<id>[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#(?P<payload>.*)$")


def parse_cansend(text: str) -> can.Message:
    """The frame of a cansend `ID#DATA` string; a malformed one is one HilError line."""
    if "##" in text:
        raise HilError(f"{text!r}: CAN FD frames are not supported (classic CAN only)")
    match = _CANSEND.match(text.strip())
    if match is None:
        raise HilError(
            f"{text!r}: expected ID#DATA with a 3-digit (standard) or 8-digit (extended) hex id, "
            "e.g. 181#D430000000000001 or 18FF1234#01.02"
        )
    frame_id = int(match["id"], 16)
    extended = len(match["id"]) == 8
    if not extended and frame_id > 0x7FF:
        raise HilError(f"{text!r}: standard id above 7FF; write 8 digits for an extended id")
    if extended and frame_id > 0x1FFFFFFF:
        raise HilError(f"{text!r}: extended id above 1FFFFFFF")
    payload = match["payload"]
    if payload[:1] in ("R", "r"):
        dlc_text = payload[1:]
        if dlc_text and not (len(dlc_text) == 1 and dlc_text in "012345678"):
            raise HilError(f"{text!r}: a remote frame takes R or R0..R8")
        dlc = int(dlc_text) if dlc_text else 0
        return can.Message(
            arbitration_id=frame_id, is_extended_id=extended, is_remote_frame=True, dlc=dlc
        )
    digits = payload.replace(".", "")
    if len(digits) % 2 or not re.fullmatch(r"[0-9A-Fa-f]*", digits):
        raise HilError(f"{text!r}: data must be whole bytes in hex, e.g. D4.30 or D430")
    data = bytes.fromhex(digits)
    if len(data) > 8:
        raise HilError(f"{text!r}: {len(data)} data bytes, classic CAN carries at most 8")
    return can.Message(arbitration_id=frame_id, is_extended_id=extended, data=data)


def encode_message(database: Database, name: str, assignments: list[str]) -> can.Message:
    """The frame of DBC message `name` with `signal=value` assignments, strictly checked."""
    try:
        message = database.get_message_by_name(name)
    except KeyError:
        raise HilError(f"--message {name!r}: no such message in the DBC") from None
    values: dict[str, float] = {}
    for assignment in assignments:
        signal_name, equals, text = assignment.partition("=")
        if not equals:
            raise HilError(f"{name}: {assignment!r} is not signal=value")
        try:
            signal = message.get_signal_by_name(signal_name)
        except KeyError:
            known = ", ".join(s.name for s in message.signals)
            raise HilError(f"{name}: no signal {signal_name!r} (it has {known})") from None
        try:
            value = float(text)
        except ValueError:
            raise HilError(f"{name}.{signal_name}: {text!r} is not a number") from None
        low, high = signal.minimum, signal.maximum
        if low is not None and high is not None and not low <= value <= high:
            unit = f" {signal.unit}" if signal.unit else ""
            raise HilError(
                f"{name}.{signal_name} = {text} is out of range [{low:g}, {high:g}]{unit}"
            )
        values[signal_name] = int(value) if value.is_integer() and signal.scale == 1 else value
    missing = [s.name for s in message.signals if s.name not in values]
    if missing:
        raise HilError(f"{name}: give every signal; missing {', '.join(missing)}")
    try:
        data = message.encode(values, strict=True)
    except Exception as exc:  # cantools: EncodeError, ValueError on a value it cannot place
        raise HilError(f"{name}: {exc}") from exc
    return can.Message(arbitration_id=message.frame_id, is_extended_id=False, data=data)


def send_one(bus: can.BusABC, msg: can.Message) -> None:
    if msg.is_remote_frame and isinstance(bus, SocketCanDaemonBus):
        raise BusError(
            f"cannot send 0x{msg.arbitration_id:X}: a remote (RTR) frame cannot cross the "
            "loopback hub (its socketcand protocol carries data frames only); use a CAN "
            "interface, e.g. socketcan:vcan0"
        )
    try:
        bus.send(msg, timeout=1.0)
    except can.CanError as exc:
        raise BusError(f"cannot send 0x{msg.arbitration_id:X}: {exc}") from exc
