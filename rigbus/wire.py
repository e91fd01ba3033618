"""The wire format of softhil's binary CAN transport, shared by the hub and the client.

Kept apart from `rigbus.binary` (the python-can bus) so that the hub, which may run as its own
small process, starts without importing python-can. The format is described in
`rigbus.binary`; invariant: every record is ``HEADER`` followed by exactly ``dlc`` data bytes,
and its size field counts the bytes after itself (``HEADER.size - SIZE_FIELD + dlc``).
"""

from __future__ import annotations

import struct

VERSION = 1
"""Binary protocol version carried in the hello and its acknowledgement."""

HELLO_MAGIC = b"\x00SHB"
"""First bytes of a binary client's hello: a NUL never starts a socketcand command."""

HEADER = struct.Struct("<HIBBd")
"""Record header: size (bytes after this field), id, flags, dlc, time in s."""

SIZE_FIELD = 2
"""Bytes of the size field itself (not counted in ``size``)."""

FLAG_EXTENDED = 0x01
"""Flags bit: 29-bit (extended) arbitration id."""

MAX_DLC = 8
"""Classic CAN data length; CAN FD is not supported."""

MAX_STD_ID = 0x7FF
MAX_EXT_ID = 0x1FFFFFFF
DEFAULT_PORT = 29536
GREETING = b"< hi >"


def encode_record(can_id: int, extended: bool, data: bytes, timestamp: float) -> bytes:
    """One record for a classic CAN data frame.

    Parameters
    ----------
    can_id
        Arbitration id (11 or 29 bits).
    extended
        Whether ``can_id`` is a 29-bit id.
    data
        0..8 data bytes.
    timestamp
        Seconds (the hub writes its receive time here; a client's value is not forwarded).

    Returns
    -------
    bytes
        ``HEADER`` followed by the data.
    """
    n = len(data)
    return HEADER.pack(HEADER.size - SIZE_FIELD + n, can_id, extended, n, timestamp) + data


def ack() -> bytes:
    """The hub's answer to a valid hello."""
    return HELLO_MAGIC + bytes((VERSION, 0))


def hello(name: str) -> bytes:
    """A binary client's hello joining hub channel ``name`` (1..64 printable ASCII)."""
    raw = name.encode("ascii")
    return HELLO_MAGIC + bytes((VERSION, len(raw))) + raw
