"""Loopback CAN hub: an inter-process CAN bus over TCP speaking socketcand and softhil's binary.

The kernel softhil runs on has no SocketCAN, so processes share a CAN bus through this hub
instead. It implements the server side of the socketcand ASCII protocol (rawmode only), which
is exactly what python-can's client needs::

    bus = can.Bus(interface="socketcand", channel="sim0", host="127.0.0.1", port=port,
                  tcp_tune=True)

Every frame a client sends on a channel is forwarded to every *other* rawmode client that
opened the same channel (no echo to the sender, like a CAN socket without RECV_OWN_MSGS).

The same port also serves softhil's binary transport (`rigbus.binary`, python-can interface
``softhil``): a connection whose first bytes are the binary hello instead of ``< open NAME >``
joins the named channel and exchanges length-prefixed records. Both kinds of client share the
channels: each frame is encoded once per protocol that some receiver speaks. The limits below
(clients, buffer shares, warnings) count both kinds alike.

Key invariant: the bus is **ordered, lossless and loopback-only**.

* Ordered: a single-threaded ``selectors`` loop handles all sockets, so every client receives
  the frames of a channel in the one global order in which the hub received them.
* Lossless: frames are never dropped for a connected client. The hub buffers at most
  ``max_buffer_bytes`` of outgoing frames in total: each of at most ``max_clients`` connections
  may hold an equal share (``max_buffer_bytes // max_clients``). A client that stops reading
  until its share is full is disconnected (counted in :attr:`LoopbackHub.slow_clients_dropped`,
  logged), rather than silently losing frames while it stays connected: a closed connection is
  a loss its owner can see, a gap in a lockstep stream would surface later as a confusing
  protocol error. The well-behaved clients never wait for it.
* Bounded: a connection beyond ``max_clients`` is refused with ``< error ... >``. The hub's own
  warnings are rate-limited per kind (``log_burst`` per ``log_interval`` seconds, then one
  "suppressed N similar" line), so a flood of junk costs CPU time but not a flood of log lines.
* Loopback-only: the hub binds to 127.0.0.1 by default; a non-loopback address must be asked
  for explicitly with ``allow_remote=True``.

python-can's client reads each handshake reply with one ``recv(256)`` and compares it exactly,
so after the rawmode ``< ok >`` the hub holds (buffers, never drops) frames for that client for
a short grace period before flushing them, so they cannot share a TCP read with the ``< ok >``.

Zero-length frames are forwarded in socketcand's own format (``< frame 123 SEC.USEC  >``, with
an empty data field), which python-can 4.6.1 parses correctly; softhil itself never sends
zero-length frames. Remote (RTR), error and CAN FD frames are not supported.

This module is the hub's public surface; the hub itself is split by concern:

* `server`: `LoopbackHub`, the listening socket, the selector loop, the clients, the lifecycle
  (its own thread, the caller's, or hosted in its owner's thread);
* `fanout`: the channels, the forwarding of each frame to the other members in their
  protocols, the output buffered within each client's share, the handshake grace;
* `socketcand`: the ASCII protocol (its summary is there), parsed and formatted;
* `binary`: softhil's binary records (`rigbus.wire`);
* `limits`: the settings and their checks, the count of what they refused, the warnings' rate
  limit;
* `members`: a connection's state, and the hosting owner's;
* `standalone`: the command line, the signals, `HubProcess`.

Run standalone with ``python -m hil.bus.loopback [--host H] [--port P] [--max-clients N]
[--max-buffer BYTES]``. Every module logs to the one logger ``hil.bus.loopback``.
"""

from __future__ import annotations

from hil.bus.loopback.limits import (
    DEFAULT_HANDSHAKE_GRACE,
    DEFAULT_LOG_BURST,
    DEFAULT_LOG_INTERVAL,
    DEFAULT_MAX_BUFFER_BYTES,
    DEFAULT_MAX_CLIENTS,
    MIN_CLIENT_SHARE,
    HubSettingError,
)
from hil.bus.loopback.members import HostedMember
from hil.bus.loopback.server import LoopbackHub
from hil.bus.loopback.standalone import DEFAULT_PORT, HubProcess, main, parse_byte_size, serve

__all__ = [
    "DEFAULT_HANDSHAKE_GRACE",
    "DEFAULT_LOG_BURST",
    "DEFAULT_LOG_INTERVAL",
    "DEFAULT_MAX_BUFFER_BYTES",
    "DEFAULT_MAX_CLIENTS",
    "DEFAULT_PORT",
    "MIN_CLIENT_SHARE",
    "HostedMember",
    "HubProcess",
    "HubSettingError",
    "LoopbackHub",
    "main",
    "parse_byte_size",
    "serve",
]
