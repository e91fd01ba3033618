"""The loopback hub's socketcand side: the ASCII protocol's hub end, rawmode only.

This is exactly what python-can's ``socketcand`` client needs::

    hub -> client   < hi >                      on connect
    client -> hub   < open NAME >               hub replies < ok >
    client -> hub   < rawmode >                 hub replies < ok >
    client -> hub   < send ID LEN B0 B1 ... >   ID hex (3 digits std / 8 ext), LEN hex 0..8,
                                                bytes hex without zero padding
    hub -> client   < frame ID SEC.USEC HEX >   ID 3 (std) or 8 (ext) uppercase hex digits,
                                                SEC.USEC hub ``time.time()``, HEX contiguous

`SocketcandSide` parses a client's input into messages and answers them; `format_frame` writes
the frames the hub forwards to such a client.

Key invariant: text is resynchronised, never fatal: anything outside ``< >``, an unterminated
or unknown message, a bad field is counted and logged (rate-limited) and skipped up to the next
``<``; a client still in its handshake is told ``< error ... >`` so that python-can's
constructor fails at once instead of waiting for a reply. Input without a closing ``>`` is
bounded (`MAX_PENDING_INPUT`).
"""

from __future__ import annotations

import logging
import re
from typing import TYPE_CHECKING

from hil.bus.loopback.members import CHANNEL_NAME, Client
from rigbus.wire import MAX_DLC, MAX_EXT_ID, MAX_STD_ID

if TYPE_CHECKING:
    from hil.bus.loopback.fanout import Fanout
    from hil.bus.loopback.limits import Accounting

log = logging.getLogger(__package__)  # the hub's one logger, hil.bus.loopback

HI = b"< hi >"
"""The hub's greeting to every new connection (a binary client reads it too)."""

OK = b"< ok >"
"""The reply to a valid ``open`` and ``rawmode``."""

MAX_PENDING_INPUT = 4096
"""Bytes of input without a closing '>' before they are discarded."""

_HEX_TOKEN = re.compile(rb"[0-9A-Fa-f]{1,2}")
_HEX_ID = re.compile(rb"[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8}")


def format_frame(can_id: int, extended: bool, data: bytes, now_ns: int) -> bytes:
    """One ``< frame ... >`` message as socketcand writes it.

    Parameters
    ----------
    can_id
        Arbitration id (11 or 29 bits).
    extended
        Whether ``can_id`` is a 29-bit id.
    data
        0..8 data bytes (none: an empty data field, as socketcand writes it).
    now_ns
        The hub's receive time [ns since the epoch].
    """
    sec, nsec = divmod(now_ns, 1_000_000_000)
    # As socketcand: "%03X"/"%08X" id, "%ld.%06ld" time, "%02X" per byte.
    return b"< frame %s %d.%06d %s >" % (
        b"%08X" % can_id if extended else b"%03X" % can_id,
        sec,
        nsec // 1000,
        data.hex().upper().encode(),
    )


class SocketcandSide:
    """The hub's socketcand protocol: handshake, ``send`` messages in, replies out.

    Parameters
    ----------
    fanout
        Where joined clients are registered and sent frames forwarded.
    accounting
        Where malformed input is counted and logged.
    """

    def __init__(self, fanout: Fanout, accounting: Accounting) -> None:
        self._fanout = fanout
        self._accounting = accounting

    def on_input(self, client: Client) -> None:
        """Handle the complete messages in ``client.inbuf``; keep an unfinished one there."""
        buf = client.inbuf
        pos = 0
        n = len(buf)
        while pos < n:
            start = buf.find(b"<", pos)
            if start < 0:
                self._junk(client, bytes(buf[pos:]))
                pos = n
                break
            if start > pos:
                self._junk(client, bytes(buf[pos:start]))
            end = buf.find(b">", start + 1)
            if end < 0:
                pos = start
                break
            nested = buf.rfind(b"<", start + 1, end)
            if nested >= 0:  # '<' ... '<' ... '>': the first part is an unterminated message
                self._malformed(client, bytes(buf[start:nested]), "unterminated message")
                start = nested
            self._handle(client, bytes(buf[start + 1 : end]))
            if client.closed:
                return
            pos = end + 1
        del buf[:pos]
        if len(buf) > MAX_PENDING_INPUT:
            self._malformed(client, bytes(buf), "no closing '>'; discarded")
            buf.clear()

    def _junk(self, client: Client, text: bytes) -> None:
        if text.strip():
            self._malformed(client, text, "text outside < >")

    def _malformed(self, client: Client, text: bytes, why: str) -> None:
        self._accounting.malformed_input(client.addr, text, why)

    def _handle(self, client: Client, body: bytes) -> None:
        """Handle one message; ``body`` is the text between ``<`` and ``>``."""
        tokens = body.split()
        if not tokens:
            self._malformed(client, b"<" + body + b">", "empty message")
            return
        cmd = tokens[0]
        if cmd == b"send":
            self._on_send(client, tokens, body)
        elif cmd == b"open":
            self._on_open(client, tokens, body)
        elif cmd == b"rawmode":
            self._on_rawmode(client, tokens, body)
        else:
            self._reject(client, body, "unknown command")

    def _reject(self, client: Client, body: bytes, why: str) -> None:
        """Log a malformed/refused message; tell handshaking clients so they fail fast."""
        self._malformed(client, b"<" + body + b">", why)
        if not client.rawmode:
            # python-can's client blocks in recv() waiting for its handshake reply; an error
            # reply makes its constructor raise instead of hanging. Not sent in rawmode, where
            # python-can would parse "< error ... >" as an error frame.
            self._fanout.queue(client, b"< error " + why.encode("ascii") + b" >")

    def _on_open(self, client: Client, tokens: list[bytes], body: bytes) -> None:
        if len(tokens) != 2 or not CHANNEL_NAME.fullmatch(tokens[1]):
            self._reject(client, body, "invalid open")
            return
        if client.channel is not None:
            self._reject(client, body, "channel already open")
            return
        client.channel = tokens[1]
        log.debug("client %s opened channel %s", client.addr, tokens[1].decode())
        self._fanout.queue(client, OK)

    def _on_rawmode(self, client: Client, tokens: list[bytes], body: bytes) -> None:
        if len(tokens) != 1:
            self._reject(client, body, "invalid rawmode")
            return
        if client.channel is None:
            self._reject(client, body, "rawmode before open")
            return
        if client.rawmode:
            self._reject(client, body, "already in rawmode")
            return
        self._fanout.queue(client, OK)  # before the hold: the ok itself is not held back
        self._fanout.join(client, client.channel)
        self._fanout.hold(client)
        log.debug("client %s entered rawmode on %s", client.addr, client.channel.decode())

    def _on_send(self, client: Client, tokens: list[bytes], body: bytes) -> None:
        if client.channel is None:
            self._reject(client, body, "send before open")
            return
        if len(tokens) < 3:
            self._reject(client, body, "invalid send")
            return
        id_tok, len_tok = tokens[1], tokens[2]
        byte_toks = tokens[3:]
        if (
            not _HEX_ID.fullmatch(id_tok)
            or not _HEX_TOKEN.fullmatch(len_tok)
            or not all(_HEX_TOKEN.fullmatch(t) for t in byte_toks)
        ):
            self._reject(client, body, "invalid send: bad hex field")
            return
        can_id = int(id_tok, 16)
        extended = len(id_tok) == 8
        if can_id > (MAX_EXT_ID if extended else MAX_STD_ID):
            self._reject(client, body, "invalid send: id out of range")
            return
        dlc = int(len_tok, 16)
        if dlc > MAX_DLC or dlc != len(byte_toks):
            self._reject(client, body, "invalid send: length mismatch")
            return
        data = bytes(int(t, 16) for t in byte_toks)
        self._fanout.forward(client, can_id, extended, data)
