"""The loopback hub's binary side: softhil's length-prefixed records (`rigbus.wire`).

A client that speaks `rigbus.binary` (python-can interface ``softhil``) starts with the binary
hello instead of ``< open NAME >``: magic, version, channel name. The hub acknowledges it and
from then on reads and writes records: a fixed header (size, id, flags, dlc, time) and the data.
`starts_binary` is how the hub tells the two protocols apart on their shared port.

Key invariant: a binary stream cannot be resynchronised, so anything malformed (a bad hello, a
record whose size, dlc, flags or id is out of range) is logged and its sender disconnected,
after a one-line ``< error ... >`` reason if it has not joined yet (`rigbus.binary.SofthilBus`
raises it as its handshake failure). Only whole records are forwarded.
"""

from __future__ import annotations

import contextlib
import logging
from typing import TYPE_CHECKING

from hil.bus.loopback.members import CHANNEL_NAME, Client
from rigbus.wire import FLAG_EXTENDED, HEADER, HELLO_MAGIC, MAX_DLC, MAX_EXT_ID, MAX_STD_ID
from rigbus.wire import SIZE_FIELD as _SIZE_FIELD
from rigbus.wire import VERSION as _BINARY_VERSION
from rigbus.wire import ack as _binary_ack

if TYPE_CHECKING:
    from hil.bus.loopback.fanout import Fanout
    from hil.bus.loopback.limits import Accounting

log = logging.getLogger(__package__)  # the hub's one logger, hil.bus.loopback

_HELLO_FIXED = len(HELLO_MAGIC) + 2  # magic, version, name length


def starts_binary(client: Client) -> bool:
    """Whether ``client``'s input is softhil's binary protocol: it joined with a binary hello,
    or it has not joined yet and its input starts with a NUL (the hello's first byte), which
    never starts a socketcand command."""
    return client.binary or (not client.rawmode and client.inbuf[:1] == b"\0")


class BinarySide:
    """The hub's binary protocol: the hello, then records in; their frames forwarded.

    Parameters
    ----------
    fanout
        Where joined clients are registered and received frames forwarded.
    accounting
        Where malformed input is counted and logged.
    """

    def __init__(self, fanout: Fanout, accounting: Accounting) -> None:
        self._fanout = fanout
        self._accounting = accounting

    def on_input(self, client: Client) -> None:
        """Handle a binary client's input: its hello, then whole records (rigbus.binary).

        An unfinished hello or record stays in ``client.inbuf`` for the next read.
        """
        buf = client.inbuf
        if not client.binary:
            if len(buf) < _HELLO_FIXED:
                if not HELLO_MAGIC.startswith(bytes(buf[: len(HELLO_MAGIC)])):
                    self._failure(client, bytes(buf), "not a binary hello")
                return
            name_len = buf[_HELLO_FIXED - 1]
            if len(buf) < _HELLO_FIXED + name_len:
                return
            self._on_hello(client, bytes(buf[: _HELLO_FIXED + name_len]))
            del buf[: _HELLO_FIXED + name_len]
            if client.closed:
                return
        pos = 0
        n = len(buf)
        header = HEADER
        while n - pos >= header.size:
            size, can_id, flags, dlc, _ = header.unpack_from(buf, pos)
            if (
                size != header.size - _SIZE_FIELD + dlc
                or dlc > MAX_DLC
                or flags & ~FLAG_EXTENDED
                or can_id > (MAX_EXT_ID if flags else MAX_STD_ID)
            ):
                self._failure(
                    client,
                    bytes(buf[pos : pos + header.size]),
                    f"bad record (size {size}, id 0x{can_id:X}, flags 0x{flags:02X}, dlc {dlc})",
                )
                return
            end = pos + _SIZE_FIELD + size
            if end > n:
                break
            self._fanout.forward(client, can_id, bool(flags), bytes(buf[end - dlc : end]))
            pos = end
        del buf[:pos]

    def _on_hello(self, client: Client, hello: bytes) -> None:
        version, name = hello[len(HELLO_MAGIC)], hello[_HELLO_FIXED:]
        if not hello.startswith(HELLO_MAGIC):
            self._failure(client, hello, "not a binary hello")
        elif version != _BINARY_VERSION:
            self._failure(client, hello, f"binary protocol version {version} unsupported")
        elif client.channel is not None:
            self._failure(client, hello, "binary hello after open")
        elif not CHANNEL_NAME.fullmatch(name):
            self._failure(client, hello, "invalid channel name")
        else:
            client.channel = name
            client.binary = True
            self._fanout.join(client, name)
            self._fanout.queue(client, _binary_ack())
            log.debug("binary client %s joined channel %s", client.addr, name.decode())

    def _failure(self, client: Client, text: bytes, why: str) -> None:
        """Log malformed binary input and disconnect its sender (after a one-line reason if
        it has not joined yet: SofthilBus raises it as its handshake failure)."""
        self._accounting.malformed_input(client.addr, text, why)
        if not client.binary:
            with contextlib.suppress(OSError):
                client.sock.send(b"< error " + why.encode("ascii") + b" >")
        self._fanout.doom(client)
