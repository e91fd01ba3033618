"""The members of the loopback hub's channels: a TCP connection, or the hub's hosting owner.

A `Client` is one connection, in whichever protocol it speaks (socketcand text or softhil's
binary records); a `HostedMember` is the owner of a hub served from its own thread
(`LoopbackHub.host`), whose frames go to an in-memory inbox instead of a socket. Both carry the
attributes the fan-out reads (``channel``, ``rawmode``, ``binary``, ``local``, ``closed``).

Key invariant: a client's `Client.pending` is exactly the bytes the hub's buffer accounting
counts for it (its output not yet written plus the frames held during its handshake grace).
"""

from __future__ import annotations

import collections
import re
import socket

CHANNEL_NAME = re.compile(rb"[!-;=?-~]{1,64}")
"""A channel's name, in either protocol: printable ASCII without '<' and '>', 1..64 bytes."""


class Client:
    """State of one TCP connection to the hub."""

    __slots__ = (
        "addr",
        "binary",
        "channel",
        "closed",
        "held",
        "hold_until",
        "inbuf",
        "local",
        "outbuf",
        "rawmode",
        "sock",
        "want_write",
    )

    def __init__(self, sock: socket.socket, addr: str) -> None:
        self.sock = sock
        self.addr = addr
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        # Frames held back during the post-rawmode grace period (None when not holding).
        self.held: bytearray | None = None
        self.hold_until = 0.0
        self.channel: bytes | None = None
        self.rawmode = False  # joined a channel (socketcand rawmode, or a binary hello)
        self.binary = False  # speaks softhil's binary records (rigbus.binary)
        self.want_write = False
        self.closed = False
        self.local = False

    def pending(self) -> int:
        """Return the number of outgoing bytes buffered for this client."""
        return len(self.outbuf) + (len(self.held) if self.held is not None else 0)


class HostedMember:
    """The hub's own member of a channel, for a hub hosted in its owner's thread
    (`LoopbackHub.host`): frames forwarded to it wait in `inbox` as (id, extended, data,
    hub time [s]) until the owner takes them; nothing is written to a socket. With `watch_id`
    set, `watched` is the client that last sent it a frame of that id (its `closed` and `addr`
    say whether and where it is connected)."""

    __slots__ = (
        "addr",
        "binary",
        "channel",
        "closed",
        "inbox",
        "local",
        "rawmode",
        "watch_id",
        "watched",
    )

    def __init__(self, channel: bytes) -> None:
        self.addr = "host"
        self.channel: bytes | None = channel
        self.inbox: collections.deque[tuple[int, bool, bytes, float]] = collections.deque()
        self.binary = self.rawmode = self.local = True
        self.closed = False
        self.watch_id: int | None = None
        self.watched: Client | None = None


Member = Client | HostedMember
"""Whatever can be on a channel's list of members."""
