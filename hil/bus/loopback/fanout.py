"""The loopback hub's channels and output: who hears a frame, and the bytes waiting for each.

`Fanout` keeps the members of every channel, forwards each frame a member sends to all the
others, each in its own protocol (socketcand text, softhil's binary records, or the hosting
owner's inbox), and buffers what the sockets have not taken yet, within each client's share of
``max_buffer_bytes``; it holds a socketcand client's frames during its handshake grace. It knows
nothing of the selector: it asks the server to watch a socket for writing through a callback,
and leaves the closing of the clients it gives up on (`doomed`) to the server's loop.

Key invariant: the bus is ordered and lossless for a connected client. Frames are queued in the
order `forward` is called, each encoding built once per frame and only if some member needs it;
a frame is never dropped for a client that stays connected: a client whose share would overflow
is disconnected instead (`Accounting.slow_client`). `buffered` is always the sum of every
client's `Client.pending`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from hil.bus.loopback.limits import Accounting
from hil.bus.loopback.members import Client, HostedMember, Member
from hil.bus.loopback.socketcand import format_frame
from rigbus.wire import encode_record

log = logging.getLogger(__package__)  # the hub's one logger, hil.bus.loopback


class Fanout:
    """The channels of a hub and the output buffered for its clients.

    Parameters
    ----------
    accounting
        The hub's limits (each client's share, the handshake grace) and where the slow
        clients it drops are counted.
    watch_write
        Called with ``(client, want)`` when a client starts (``want``) or stops having output
        the kernel did not take: the server watches its socket for writing meanwhile.
    """

    def __init__(self, accounting: Accounting, watch_write: Callable[[Client, bool], None]) -> None:
        self._accounting = accounting
        self._share = accounting.limits.share
        self._grace = accounting.limits.handshake_grace
        self._watch_write = watch_write
        self.channels: dict[bytes, list[Member]] = {}  # the members of each channel
        self.joined: set[bytes] = set()  # every channel a client has joined
        self.dirty: dict[int, Client] = {}  # clients with output to flush (insertion order)
        self.holding: dict[int, Client] = {}  # clients in the handshake grace period
        self.doomed: list[Client] = []  # clients to disconnect at the end of this turn
        self.frames_forwarded = 0
        """Frames received from members and fanned out (each once, whatever its receivers)."""
        self.rawmode_clients = 0
        """Connected clients that joined a channel (the hosting member not counted)."""
        self.buffered = 0
        """Outgoing bytes in all clients' output and held frames."""
        self.buffered_peak = 0
        """The highest `buffered` so far."""

    # ------------------------------------------------------------------ membership

    def join(self, client: Client, channel: bytes) -> None:
        """Make ``client`` a member of ``channel``: it hears the channel's frames from now."""
        client.rawmode = True
        self.rawmode_clients += 1
        self.channels.setdefault(channel, []).append(client)
        self.joined.add(channel)

    def host(self, member: HostedMember) -> None:
        """Make the hosting owner a member of its channel (not counted among the clients)."""
        assert member.channel is not None
        self.channels.setdefault(member.channel, []).append(member)

    def hold(self, client: Client) -> None:
        """Hold ``client``'s frames for the handshake grace (none if the grace is 0)."""
        if self._grace > 0:
            client.held = bytearray()
            client.hold_until = time.monotonic() + self._grace
            self.holding[id(client)] = client

    def leave(self, client: Client) -> None:
        """Forget ``client``: its buffered output, its holding, its channel membership."""
        self.buffered -= client.pending()
        client.outbuf.clear()
        client.held = None
        self.dirty.pop(id(client), None)
        self.holding.pop(id(client), None)
        if client.rawmode and client.channel is not None:
            members = self.channels.get(client.channel, [])
            if client in members:
                members.remove(client)
                self.rawmode_clients -= 1
            if not members:
                self.channels.pop(client.channel, None)

    def doom(self, client: Client) -> None:
        """Stop queueing for ``client``; the server closes it at the end of this turn (not now:
        this may run inside the fan-out over its channel's members)."""
        client.closed = True
        self.doomed.append(client)

    # ------------------------------------------------------------------ fan-out

    def forward(self, sender: Member, can_id: int, extended: bool, data: bytes) -> None:
        """Queue one frame for every other member of ``sender``'s channel, each in its protocol.

        Each encoding is built once per frame and only if some member needs it.
        """
        now = time.time_ns()
        text = record = None
        self.frames_forwarded += 1
        for other in self.channels.get(sender.channel, ()):  # type: ignore[arg-type]
            if other is sender:
                continue
            if other.local:
                other.inbox.append((can_id, extended, data, now / 1e9))  # type: ignore[union-attr]
                if can_id == other.watch_id:  # type: ignore[union-attr]
                    other.watched = sender  # type: ignore[union-attr]
                continue
            if other.binary:
                if record is None:
                    record = encode_record(can_id, extended, data, now / 1e9)
                self.queue(other, record)  # type: ignore[arg-type]
            else:
                if text is None:
                    text = format_frame(can_id, extended, data, now)
                self.queue(other, text)  # type: ignore[arg-type]

    # ------------------------------------------------------------------ output

    def queue(self, client: Client, data: bytes) -> None:
        """Buffer ``data`` for ``client``, or disconnect it if that would exceed its share."""
        if client.closed:
            return
        size = len(data)
        if client.pending() + size > self._share:
            if client.held is None and client.outbuf:
                self.flush(client)  # the kernel may take some now: only a stalled client fails
            if client.closed:
                return
            if client.pending() + size > self._share:
                self._accounting.slow_client(client.addr, client.pending(), size)
                self.doom(client)
                return
        if client.held is not None:
            client.held += data
        else:
            client.outbuf += data
            self.dirty[id(client)] = client
        self.buffered += size
        if self.buffered > self.buffered_peak:
            self.buffered_peak = self.buffered

    def release_due(self) -> float | None:
        """Monotonic time at which the first handshake grace ends (None: nobody is held)."""
        return min(c.hold_until for c in self.holding.values()) if self.holding else None

    def release_held(self) -> None:
        """Pass the held frames of the clients whose grace has ended on to their output."""
        now = time.monotonic()
        for key, client in list(self.holding.items()):
            if client.hold_until > now:
                continue
            if client.outbuf:
                # The "< ok >" itself has not left yet: keep holding so the frames cannot
                # end up in the same TCP read as the ok.
                client.hold_until = now + self._grace
                continue
            del self.holding[key]
            held, client.held = client.held, None
            if held:
                client.outbuf += held
                self.dirty[id(client)] = client

    def flush_dirty(self) -> None:
        """Write what every client with new output can take now."""
        if not self.dirty:
            return
        dirty = list(self.dirty.values())
        self.dirty.clear()
        for client in dirty:
            if not client.closed:
                self.flush(client)

    def flush(self, client: Client) -> None:
        """Write as much of ``client``'s output as its socket takes without blocking."""
        buf = client.outbuf
        while buf:
            try:
                sent = client.sock.send(buf)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                log.info("client %s: send failed (%s); disconnecting", client.addr, exc)
                self.doom(client)
                return
            del buf[:sent]
            self.buffered -= sent
        want = bool(buf)
        if want != client.want_write:
            client.want_write = want
            self._watch_write(client, want)
