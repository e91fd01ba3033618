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

Protocol summary (hub side)::

    hub -> client   < hi >                      on connect
    client -> hub   < open NAME >               hub replies < ok >
    client -> hub   < rawmode >                 hub replies < ok >
    client -> hub   < send ID LEN B0 B1 ... >   ID hex (3 digits std / 8 ext), LEN hex 0..8,
                                                bytes hex without zero padding
    hub -> client   < frame ID SEC.USEC HEX >   ID 3 (std) or 8 (ext) uppercase hex digits,
                                                SEC.USEC hub ``time.time()``, HEX contiguous

python-can's client reads each handshake reply with one ``recv(256)`` and compares it exactly,
so after the rawmode ``< ok >`` the hub holds (buffers, never drops) frames for that client for
a short grace period before flushing them, so they cannot share a TCP read with the ``< ok >``.

Zero-length frames are forwarded in socketcand's own format (``< frame 123 SEC.USEC  >``, with
an empty data field), which python-can 4.6.1 parses correctly; softhil itself never sends
zero-length frames. Remote (RTR), error and CAN FD frames are not supported.

Run standalone with ``python -m hil.bus.loopback [--host H] [--port P] [--max-clients N]
[--max-buffer BYTES]``.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import errno
import ipaddress
import logging
import re
import selectors
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterable
from types import FrameType, TracebackType
from typing import Self

from hil.errors import BusError, HilError
from rigbus.wire import FLAG_EXTENDED as _FLAG_EXTENDED
from rigbus.wire import HEADER as _RECORD_HEADER
from rigbus.wire import HELLO_MAGIC as _HELLO_MAGIC
from rigbus.wire import SIZE_FIELD as _SIZE_FIELD
from rigbus.wire import VERSION as _BINARY_VERSION
from rigbus.wire import ack as _binary_ack
from rigbus.wire import encode_record

__all__ = ["DEFAULT_PORT", "HubProcess", "HubSettingError", "LoopbackHub", "main"]

log = logging.getLogger(__name__)

DEFAULT_PORT = 29536
"""Default TCP port of the standalone hub (``python -m hil.bus.loopback``)."""

DEFAULT_MAX_CLIENTS = 64
"""Connections the hub serves at once; more are refused."""

DEFAULT_MAX_BUFFER_BYTES = 64 * 1024 * 1024
"""Outgoing bytes the hub buffers for all clients together (each may use an equal share)."""

MIN_CLIENT_SHARE = 64 * 1024
"""Smallest per-client share of the buffer allowed: below it, a client that reads but lags a
moment behind a fast sender (its kernel socket buffer full) would be taken for a stalled one."""

DEFAULT_LOG_BURST = 20
"""Warnings of one kind logged per ``DEFAULT_LOG_INTERVAL`` before the rest are only counted."""

DEFAULT_LOG_INTERVAL = 10.0
"""Seconds of the warning rate limit's window."""

DEFAULT_HANDSHAKE_GRACE = 0.05
"""Seconds frames are held for a client after its rawmode ``< ok >``."""

_RECV_SIZE = 256 * 1024
_MAX_PENDING_INPUT = 4096  # bytes of input without a closing '>' before it is discarded
_MAX_LOGGED_TEXT = 200
_MAX_STD_ID = 0x7FF
_MAX_EXT_ID = 0x1FFFFFFF
_MAX_DLC = 8

_HELLO_FIXED = len(_HELLO_MAGIC) + 2  # magic, version, name length

_HEX_TOKEN = re.compile(rb"[0-9A-Fa-f]{1,2}")
_HEX_ID = re.compile(rb"[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8}")
_CHANNEL_NAME = re.compile(rb"[!-;=?-~]{1,64}")  # printable ASCII without '<' and '>'


class HubSettingError(BusError, ValueError):
    """A hub setting (host, port, a limit) is invalid; one line naming the setting.

    Also a ``ValueError``, the type the hub raised for bad settings before there was this class.
    """


def _check_host(host: str, allow_remote: bool) -> None:
    """Raise `HubSettingError` unless ``host`` is an IPv4 loopback address or remote is allowed.

    Parameters
    ----------
    host
        IPv4 address or host name to bind to.
    allow_remote
        Whether binding to a non-loopback address is permitted.
    """
    try:
        infos = socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise HubSettingError(
            f"cannot resolve hub host {host!r} to an IPv4 address: {exc}"
        ) from exc
    addresses = {str(info[4][0]) for info in infos}
    if allow_remote:
        return
    remote = sorted(a for a in addresses if not ipaddress.ip_address(a).is_loopback)
    if remote:
        raise HubSettingError(
            f"refusing to bind the loopback CAN hub to non-loopback address {host!r} "
            f"({', '.join(remote)}): this would expose the CAN bus to the network; "
            "pass allow_remote=True (CLI: --allow-remote) if that is really intended"
        )


def _check_settings(
    port: int,
    max_clients: int,
    max_buffer_bytes: int,
    handshake_grace: float,
    log_burst: int,
    log_interval: float,
) -> None:
    """Raise `HubSettingError` naming the first setting that is out of range."""
    if not 0 <= port <= 65535:
        raise HubSettingError(f"hub port must be in 0..65535 (0 = any free port), got {port}")
    if max_clients < 1:
        raise HubSettingError(f"max_clients must be at least 1, got {max_clients}")
    if max_buffer_bytes // max_clients < MIN_CLIENT_SHARE:
        raise HubSettingError(
            f"max_buffer_bytes {max_buffer_bytes} leaves each of max_clients {max_clients} "
            f"clients less than {MIN_CLIENT_SHARE} bytes; "
            f"use at least {MIN_CLIENT_SHARE * max_clients}"
        )
    if not handshake_grace >= 0:
        raise HubSettingError(f"handshake_grace must be >= 0 s, got {handshake_grace}")
    if log_burst < 1:
        raise HubSettingError(f"log_burst must be at least 1, got {log_burst}")
    if not log_interval > 0:
        raise HubSettingError(f"log_interval must be > 0 s, got {log_interval}")


class _RateLimitedLog:
    """The hub's warnings, at most ``burst`` per ``interval`` seconds of each kind.

    The first ``burst`` messages of a kind in a window are logged; the rest are only counted,
    and when the window ends (or the hub stops) one line says how many were suppressed. Windows
    start at the first message of a kind, so a quiet hub logs every warning.
    """

    def __init__(
        self, logger: logging.Logger, burst: int, interval: float, clock: Callable[[], float]
    ) -> None:
        self._log = logger
        self._burst = burst
        self._interval = interval
        self._clock = clock
        self._windows: dict[str, list[float]] = {}  # kind -> [window end, logged, suppressed]
        self.suppressed = 0
        """Messages suppressed so far, all kinds."""

    def log(self, level: int, kind: str, message: str, *args: object) -> None:
        """Log ``message % args`` at ``level`` unless this kind's budget is used up."""
        now = self._clock()
        window = self._windows.get(kind)
        if window is not None and now >= window[0]:
            self._summarise(kind, window)
            window = None
        if window is None:
            window = self._windows[kind] = [now + self._interval, 0, 0]
        if window[1] < self._burst:
            window[1] += 1
            self._log.log(level, message, *args)
        else:
            window[2] += 1
            self.suppressed += 1

    def next_deadline(self) -> float | None:
        """Monotonic time at which a pending "suppressed" line is due (None: none pending)."""
        due = [w[0] for w in self._windows.values() if w[2]]
        return min(due) if due else None

    def flush(self, *, everything: bool = False) -> None:
        """Write the "suppressed" lines of ended windows (of all windows if ``everything``)."""
        now = self._clock()
        for kind, window in list(self._windows.items()):
            if everything or now >= window[0]:
                self._summarise(kind, window)
                del self._windows[kind]

    def _summarise(self, kind: str, window: list[float]) -> None:
        if window[2]:
            self._log.warning(
                "loopback CAN hub: suppressed %d similar %s messages "
                "(at most %d per %g s are logged)",
                window[2],
                kind,
                self._burst,
                self._interval,
            )


def _bind_problem(exc: OSError) -> str:
    """What a failed bind means, in the words a user of ``--host``/``--port`` needs."""
    if exc.errno == errno.EADDRINUSE:
        return "address already in use (another hub or program listens there; choose another port)"
    if exc.errno == errno.EACCES:
        return "permission denied (ports below 1024 need privileges; choose another port)"
    if exc.errno == errno.EADDRNOTAVAIL:
        return "address not available (it is not an address of this machine)"
    return exc.strerror or str(exc)


def _shorten(text: bytes) -> str:
    """Return ``text`` as a printable, length-limited string for log messages."""
    s = text[:_MAX_LOGGED_TEXT].decode("ascii", errors="backslashreplace")
    if len(text) > _MAX_LOGGED_TEXT:
        s += f"...({len(text)} bytes)"
    return repr(s)


class _Client:
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


class _Local:
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
        self.watched: _Client | None = None


class LoopbackHub:
    """TCP hub that forwards CAN frames between socketcand (rawmode) clients.

    Parameters
    ----------
    host
        Address to bind to; 127.0.0.1 by default. IPv4 only, because python-can's
        socketcand client only speaks IPv4.
    port
        TCP port; 0 picks a free port (see :attr:`port` after :meth:`start`).
    allow_remote
        Must be ``True`` to bind to a non-loopback address.
    max_clients
        Connections served at once; further ones get ``< error ... >`` and are closed.
    max_buffer_bytes
        Outgoing bytes buffered for all clients together. Each connection may hold an equal
        share (``max_buffer_bytes // max_clients``, at least `MIN_CLIENT_SHARE`); a client whose
        unread frames would exceed its share is disconnected (see module docstring).
    handshake_grace
        Seconds to hold frames for a client after its rawmode ``< ok >`` (see module docstring).
    log_burst, log_interval
        At most ``log_burst`` warnings of one kind are logged per ``log_interval`` seconds; the
        rest are counted and summarised in one line.

    Raises
    ------
    HubSettingError
        (a ``ValueError``) If ``host`` is not a loopback address and ``allow_remote`` is
        false, cannot be resolved to an IPv4 address, or a number is out of range.

    Examples
    --------
    >>> with LoopbackHub() as hub:  # doctest: +SKIP
    ...     bus = can.Bus(interface="socketcand", channel="sim0", host="127.0.0.1",
    ...                   port=hub.port, tcp_tune=True)
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        allow_remote: bool = False,
        max_clients: int = DEFAULT_MAX_CLIENTS,
        max_buffer_bytes: int = DEFAULT_MAX_BUFFER_BYTES,
        handshake_grace: float = DEFAULT_HANDSHAKE_GRACE,
        log_burst: int = DEFAULT_LOG_BURST,
        log_interval: float = DEFAULT_LOG_INTERVAL,
    ) -> None:
        _check_settings(
            port, max_clients, max_buffer_bytes, handshake_grace, log_burst, log_interval
        )
        _check_host(host, allow_remote)
        self._host = host
        self._requested_port = port
        self._max_clients = max_clients
        self._max_buffer_bytes = max_buffer_bytes
        self._share = max_buffer_bytes // max_clients
        self._grace = handshake_grace
        self._warn = _RateLimitedLog(log, log_burst, log_interval, lambda: time.monotonic())
        self._listener: socket.socket | None = None
        self._address: tuple[str, int] | None = None
        self._selector: selectors.BaseSelector | None = None
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._loop_ident: int | None = None
        self._lock = threading.RLock()  # re-entrant: stop() may run in a signal handler
        self._stop_requested = False
        self._started = False
        self._done = threading.Event()
        self._hosted = False  # served by `poll` from its owner's thread (`host`)
        self._turning = False
        self._clients: dict[int, _Client] = {}  # keyed by socket fd
        self._channels: dict[bytes, list[_Client]] = {}  # rawmode clients per channel
        self._joined: set[bytes] = set()  # every channel a client has joined
        self._dirty: dict[int, _Client] = {}  # clients with output to flush (insertion order)
        self._holding: dict[int, _Client] = {}  # clients in the handshake grace period
        self._doomed: list[_Client] = []  # clients to disconnect at the end of this iteration
        self._frames_forwarded = 0
        self._rawmode_clients = 0
        self._buffered = 0  # outgoing bytes in all clients' outbuf and held
        self._buffered_peak = 0
        self._slow_dropped = 0
        self._refused = 0
        self._malformed_count = 0

    # ------------------------------------------------------------------ public API

    @property
    def port(self) -> int:
        """Actual bound TCP port (valid after :meth:`start` / :meth:`serve_forever`)."""
        return self.address[1]

    @property
    def address(self) -> tuple[str, int]:
        """Actual bound ``(host, port)``; raises ``RuntimeError`` before the hub is bound."""
        if self._address is None:
            raise RuntimeError("LoopbackHub is not bound yet; call start() first")
        return self._address

    def joined(self) -> list[str]:
        """The channels that clients have joined since the hub started (the hosting member's
        own excepted), sorted: where a client that named the wrong channel went."""
        return sorted(name.decode() for name in self._joined)

    @property
    def frames_forwarded(self) -> int:
        """Number of valid frames received from clients and fanned out to their channel.

        Each frame counts once, however many clients (possibly none) it was delivered to.
        """
        return self._frames_forwarded

    @property
    def clients(self) -> int:
        """Number of currently connected clients in rawmode."""
        return self._rawmode_clients

    @property
    def max_client_buffer(self) -> int:
        """Outgoing bytes one client may have buffered before it is disconnected."""
        return self._share

    @property
    def buffered_bytes(self) -> int:
        """Outgoing bytes the hub holds right now for all clients (at most ``max_buffer_bytes``)."""
        return self._buffered

    @property
    def buffered_bytes_peak(self) -> int:
        """The highest :attr:`buffered_bytes` so far."""
        return self._buffered_peak

    @property
    def slow_clients_dropped(self) -> int:
        """Clients disconnected because they did not read their frames (share exceeded)."""
        return self._slow_dropped

    @property
    def clients_refused(self) -> int:
        """Connections refused because ``max_clients`` were connected."""
        return self._refused

    @property
    def malformed_messages(self) -> int:
        """Malformed or refused pieces of client input (each one ignored)."""
        return self._malformed_count

    @property
    def warnings_suppressed(self) -> int:
        """Warnings counted but not logged by the rate limit."""
        return self._warn.suppressed

    def start(self) -> Self:
        """Bind and serve in a daemon background thread.

        Returns
        -------
        LoopbackHub
            ``self``, so that ``hub = LoopbackHub().start()`` works.
        """
        self.bind()
        with self._lock:
            self._claim_start()
            self._thread = threading.Thread(
                target=self._run, name=f"softhil-loopback-hub:{self.port}", daemon=True
            )
            self._thread.start()
        return self

    def serve_forever(self) -> None:
        """Bind (if not bound yet) and serve in the calling thread until :meth:`stop`.

        Returns immediately if :meth:`stop` was already called.
        """
        with self._lock:
            if self._stop_requested:
                return
        self.bind()
        with self._lock:
            self._claim_start()
        self._run()

    def stop(self) -> None:
        """Stop serving, close all sockets and join the serving thread. Idempotent.

        Safe to call from any thread and from a signal handler running in the serving thread
        (then it only requests the stop; the loop exits once the handler returns).
        """
        with self._lock:
            self._stop_requested = True
            started = self._started
            wake = self._wake_w
        if self._hosted:  # closed now, or by `poll` once the turn it is in ends
            if not self._turning and self._selector is not None:
                self._teardown()
            return
        if wake is not None:
            # OSError: already closed, or wake pipe full and so the loop is waking anyway.
            with contextlib.suppress(OSError):
                wake.send(b"\0")
        if not started:
            self._close_listener()
            return
        if threading.get_ident() == self._loop_ident:
            return
        self._done.wait()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    # ------------------------------------------------------------------ setup / teardown

    def _claim_start(self) -> None:
        """Mark the hub as started; must be called with ``self._lock`` held."""
        if self._started:
            raise RuntimeError("LoopbackHub is already serving (or was stopped)")
        if self._stop_requested:
            raise RuntimeError("LoopbackHub was stopped and cannot be restarted")
        self._started = True

    def bind(self) -> Self:
        """Bind the listening socket now, without serving yet. Idempotent.

        :meth:`start` and :meth:`serve_forever` bind implicitly; calling this first lets a
        caller learn :attr:`port` before serving in its own thread (connections made in
        between wait in the listen backlog).

        Returns
        -------
        LoopbackHub
            ``self``.
        """
        with self._lock:
            if self._stop_requested:
                raise RuntimeError("LoopbackHub was stopped and cannot be restarted")
            if self._listener is not None:
                return self
            listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            try:
                listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                listener.bind((self._host, self._requested_port))
                listener.listen(128)
                listener.setblocking(False)
            except OSError as exc:
                listener.close()
                raise BusError(
                    f"cannot listen on {self._host}:{self._requested_port}: {_bind_problem(exc)}"
                ) from exc
            except BaseException:
                listener.close()
                raise
            wake_r, wake_w = socket.socketpair()
            wake_r.setblocking(False)
            wake_w.setblocking(False)
            self._listener = listener
            self._wake_r, self._wake_w = wake_r, wake_w
            host, port = listener.getsockname()[:2]
            self._address = (str(host), int(port))
            log.info("loopback CAN hub bound to %s:%d", host, port)
        return self

    def _close_listener(self) -> None:
        with self._lock:
            socks = [self._listener, self._wake_r, self._wake_w]
            self._listener = self._wake_r = self._wake_w = None
        for s in socks:
            if s is not None:
                s.close()

    # ------------------------------------------------------------------ event loop

    def _run(self) -> None:
        self._loop_ident = threading.get_ident()
        listener, wake_r = self._listener, self._wake_r
        sel = selectors.DefaultSelector()
        self._selector = sel
        try:
            if listener is None or wake_r is None:  # stop() won a race with start()
                return
            sel.register(listener, selectors.EVENT_READ, None)
            sel.register(wake_r, selectors.EVENT_READ, None)
            while not self._stop_requested:
                self._turn(self._deadline())
        except Exception:
            log.exception("loopback CAN hub event loop crashed")
            raise
        finally:
            self._teardown()

    def _deadline(self) -> float | None:
        """Seconds until the loop must turn without input: a held client's grace period
        ending or a warning summary due (None: no such deadline)."""
        deadlines = [c.hold_until for c in self._holding.values()]
        summary_due = self._warn.next_deadline()
        if summary_due is not None:
            deadlines.append(summary_due)
        return max(0.0, min(deadlines) - time.monotonic()) if deadlines else None

    def _turn(self, timeout: float | None) -> None:
        """One turn of the event loop: wait at most `timeout` [s] for sockets to be ready,
        serve them, release held clients, write what is queued, drop the doomed."""
        sel, listener, wake_r = self._selector, self._listener, self._wake_r
        assert sel is not None
        summary_due = self._warn.next_deadline()
        for key, events in sel.select(timeout):
            sock = key.fileobj
            if sock is listener:
                self._accept()
            elif sock is wake_r:
                self._drain_wake()
            else:
                client = key.data
                if client.closed:
                    continue
                if events & selectors.EVENT_READ:
                    self._on_readable(client)
                if events & selectors.EVENT_WRITE and not client.closed:
                    self._dirty[id(client)] = client
        if self._holding:
            self._release_held()
        self._flush_dirty()
        for client in self._doomed:
            self._disconnect(client)
        self._doomed.clear()
        if summary_due is not None:
            self._warn.flush()

    def _teardown(self) -> None:
        for client in list(self._clients.values()):
            self._disconnect(client, quiet=True)
        self._warn.flush(everything=True)
        if self._selector is not None:
            self._selector.close()
        self._selector = None
        self._close_listener()
        self._done.set()
        log.info("loopback CAN hub stopped")

    # ------------------------------------------------------------------ hosted in a thread

    def host(self, channel: str) -> _Local:
        """Serve from the calling thread, turned by `poll` (no thread of its own), with the
        caller as a member of `channel`: what other members send it waits in the returned
        member's `inbox`, what it sends goes out through `send_from`. Close with `stop`."""
        name = channel.encode()
        if not _CHANNEL_NAME.fullmatch(name):
            raise HubSettingError(f"invalid channel name {channel!r}")
        self.bind()
        with self._lock:
            self._claim_start()
            self._loop_ident = threading.get_ident()
            self._hosted = True
        sel = selectors.DefaultSelector()
        assert self._listener is not None and self._wake_r is not None
        sel.register(self._listener, selectors.EVENT_READ, None)
        sel.register(self._wake_r, selectors.EVENT_READ, None)
        self._selector = sel
        member = _Local(name)
        self._channels.setdefault(name, []).append(member)  # type: ignore[arg-type]
        return member

    def poll(self, timeout: float | None) -> None:
        """One turn of a hosted hub's loop, waiting at most `timeout` [s] (None: until a
        socket is ready or a deadline of the hub's own comes)."""
        if self._selector is None:
            raise BusError("the hosted hub is closed")
        deadline = self._deadline()
        if deadline is not None:
            timeout = deadline if timeout is None else min(timeout, deadline)
        self._turning = True
        try:
            self._turn(timeout)
        finally:
            self._turning = False
            if self._stop_requested:
                self._teardown()

    def send_from(self, member: _Local, frames: Iterable[tuple[int, bool, bytes]]) -> None:
        """Forward frames (id, extended, data) from a hosted member to the rest of its
        channel, in order, and write them out now (what a socket does not take yet stays
        queued for the next turns)."""
        if self._selector is None:
            raise BusError("the hosted hub is closed")
        for can_id, extended, data in frames:
            self._forward(member, can_id, extended, data)  # type: ignore[arg-type]
        self._flush_dirty()
        for client in self._doomed:
            self._disconnect(client)
        self._doomed.clear()

    def _drain_wake(self) -> None:
        assert self._wake_r is not None
        try:
            while self._wake_r.recv(4096):
                pass
        except BlockingIOError:
            pass

    def _accept(self) -> None:
        assert self._listener is not None and self._selector is not None
        while True:
            try:
                sock, peer = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. EMFILE: keep serving the existing clients
                self._warn.log(logging.ERROR, "accept", "loopback CAN hub: accept failed: %s", exc)
                return
            sock.setblocking(False)
            addr = f"{peer[0]}:{peer[1]}"
            if len(self._clients) >= self._max_clients:
                self._refuse(sock, addr)
                continue
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(sock, addr)
            self._clients[sock.fileno()] = client
            self._selector.register(sock, selectors.EVENT_READ, client)
            log.debug("client %s connected", client.addr)
            self._queue(client, b"< hi >")

    def _refuse(self, sock: socket.socket, addr: str) -> None:
        """Tell a connection beyond ``max_clients`` why it is closed, then close it."""
        self._refused += 1
        self._warn.log(
            logging.WARNING,
            "refused connection",
            "loopback CAN hub: refused client %s: %d clients connected (max_clients %d)",
            addr,
            len(self._clients),
            self._max_clients,
        )
        # Best effort and non-blocking: python-can reports this text as its handshake failure.
        with contextlib.suppress(OSError):
            sock.send(b"< error too many clients (max_clients %d) >" % self._max_clients)
        sock.close()

    def _on_readable(self, client: _Client) -> None:
        try:
            data = client.sock.recv(_RECV_SIZE)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            log.info("client %s: receive failed (%s); disconnecting", client.addr, exc)
            self._disconnect(client)
            return
        if not data:
            log.debug("client %s closed the connection", client.addr)
            self._disconnect(client)
            return
        buf = client.inbuf
        buf += data
        if client.binary or (not client.rawmode and buf[:1] == b"\0"):
            self._on_binary_input(client)
            return
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
        if len(buf) > _MAX_PENDING_INPUT:
            self._malformed(client, bytes(buf), "no closing '>'; discarded")
            buf.clear()

    def _junk(self, client: _Client, text: bytes) -> None:
        if text.strip():
            self._malformed(client, text, "text outside < >")

    def _malformed(self, client: _Client, text: bytes, why: str) -> None:
        self._malformed_count += 1
        self._warn.log(
            logging.WARNING,
            "malformed input",
            "client %s sent malformed input (%s): %s",
            client.addr,
            why,
            _shorten(text),
        )

    # ------------------------------------------------------------------ protocol

    def _handle(self, client: _Client, body: bytes) -> None:
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

    def _reject(self, client: _Client, body: bytes, why: str) -> None:
        """Log a malformed/refused message; tell handshaking clients so they fail fast."""
        self._malformed(client, b"<" + body + b">", why)
        if not client.rawmode:
            # python-can's client blocks in recv() waiting for its handshake reply; an error
            # reply makes its constructor raise instead of hanging. Not sent in rawmode, where
            # python-can would parse "< error ... >" as an error frame.
            self._queue(client, b"< error " + why.encode("ascii") + b" >")

    def _on_open(self, client: _Client, tokens: list[bytes], body: bytes) -> None:
        if len(tokens) != 2 or not _CHANNEL_NAME.fullmatch(tokens[1]):
            self._reject(client, body, "invalid open")
            return
        if client.channel is not None:
            self._reject(client, body, "channel already open")
            return
        client.channel = tokens[1]
        log.debug("client %s opened channel %s", client.addr, tokens[1].decode())
        self._queue(client, b"< ok >")

    def _on_rawmode(self, client: _Client, tokens: list[bytes], body: bytes) -> None:
        if len(tokens) != 1:
            self._reject(client, body, "invalid rawmode")
            return
        if client.channel is None:
            self._reject(client, body, "rawmode before open")
            return
        if client.rawmode:
            self._reject(client, body, "already in rawmode")
            return
        self._queue(client, b"< ok >")
        client.rawmode = True
        self._rawmode_clients += 1
        self._channels.setdefault(client.channel, []).append(client)
        self._joined.add(client.channel)
        if self._grace > 0:
            client.held = bytearray()
            client.hold_until = time.monotonic() + self._grace
            self._holding[id(client)] = client
        log.debug("client %s entered rawmode on %s", client.addr, client.channel.decode())

    def _on_send(self, client: _Client, tokens: list[bytes], body: bytes) -> None:
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
        if can_id > (_MAX_EXT_ID if extended else _MAX_STD_ID):
            self._reject(client, body, "invalid send: id out of range")
            return
        dlc = int(len_tok, 16)
        if dlc > _MAX_DLC or dlc != len(byte_toks):
            self._reject(client, body, "invalid send: length mismatch")
            return
        data = bytes(int(t, 16) for t in byte_toks)
        self._forward(client, can_id, extended, data)

    def _forward(self, client: _Client, can_id: int, extended: bool, data: bytes) -> None:
        """Queue one frame for every other member of ``client``'s channel, each in its protocol.

        Each encoding is built once per frame and only if some member needs it.
        """
        now = time.time_ns()
        text = record = None
        self._frames_forwarded += 1
        for other in self._channels.get(client.channel, ()):  # type: ignore[arg-type]
            if other is client:
                continue
            if other.local:
                other.inbox.append((can_id, extended, data, now / 1e9))  # type: ignore[attr-defined]
                if can_id == other.watch_id:  # type: ignore[attr-defined]
                    other.watched = client  # type: ignore[attr-defined]
                continue
            if other.binary:
                if record is None:
                    record = encode_record(can_id, extended, data, now / 1e9)
                self._queue(other, record)
            else:
                if text is None:
                    sec, nsec = divmod(now, 1_000_000_000)
                    # As socketcand: "%03X"/"%08X" id, "%ld.%06ld" time, "%02X" per byte.
                    text = b"< frame %s %d.%06d %s >" % (
                        b"%08X" % can_id if extended else b"%03X" % can_id,
                        sec,
                        nsec // 1000,
                        data.hex().upper().encode(),
                    )
                self._queue(other, text)

    # ------------------------------------------------------------------ binary protocol

    def _on_binary_input(self, client: _Client) -> None:
        """Handle a binary client's input: its hello, then whole records (rigbus.binary).

        A binary stream cannot be resynchronised, so anything malformed is logged and the
        client disconnected (unlike socketcand text, where the hub skips to the next '<').
        """
        buf = client.inbuf
        if not client.binary:
            if len(buf) < _HELLO_FIXED:
                if not _HELLO_MAGIC.startswith(bytes(buf[: len(_HELLO_MAGIC)])):
                    self._binary_failure(client, bytes(buf), "not a binary hello")
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
        header = _RECORD_HEADER
        while n - pos >= header.size:
            size, can_id, flags, dlc, _ = header.unpack_from(buf, pos)
            if (
                size != header.size - _SIZE_FIELD + dlc
                or dlc > _MAX_DLC
                or flags & ~_FLAG_EXTENDED
                or can_id > (_MAX_EXT_ID if flags else _MAX_STD_ID)
            ):
                self._binary_failure(
                    client,
                    bytes(buf[pos : pos + header.size]),
                    f"bad record (size {size}, id 0x{can_id:X}, flags 0x{flags:02X}, dlc {dlc})",
                )
                return
            end = pos + _SIZE_FIELD + size
            if end > n:
                break
            self._forward(client, can_id, bool(flags), bytes(buf[end - dlc : end]))
            pos = end
        del buf[:pos]

    def _on_hello(self, client: _Client, hello: bytes) -> None:
        version, name = hello[len(_HELLO_MAGIC)], hello[_HELLO_FIXED:]
        if not hello.startswith(_HELLO_MAGIC):
            self._binary_failure(client, hello, "not a binary hello")
        elif version != _BINARY_VERSION:
            self._binary_failure(client, hello, f"binary protocol version {version} unsupported")
        elif client.channel is not None:
            self._binary_failure(client, hello, "binary hello after open")
        elif not _CHANNEL_NAME.fullmatch(name):
            self._binary_failure(client, hello, "invalid channel name")
        else:
            client.channel = name
            client.binary = client.rawmode = True
            self._rawmode_clients += 1
            self._channels.setdefault(name, []).append(client)
            self._joined.add(name)
            self._queue(client, _binary_ack())
            log.debug("binary client %s joined channel %s", client.addr, name.decode())

    def _binary_failure(self, client: _Client, text: bytes, why: str) -> None:
        """Log malformed binary input and disconnect its sender (after a one-line reason if
        it has not joined yet: SofthilBus raises it as its handshake failure)."""
        self._malformed(client, text, why)
        if not client.binary:
            with contextlib.suppress(OSError):
                client.sock.send(b"< error " + why.encode("ascii") + b" >")
        client.closed = True
        self._doomed.append(client)

    # ------------------------------------------------------------------ output

    def _queue(self, client: _Client, data: bytes) -> None:
        """Buffer ``data`` for ``client``, or disconnect it if that would exceed its share."""
        if client.closed:
            return
        size = len(data)
        if client.pending() + size > self._share:
            if client.held is None and client.outbuf:
                self._flush(client)  # the kernel may take some now: only a stalled client fails
            if client.closed:
                return
            if client.pending() + size > self._share:
                self._drop_slow(client, size)
                return
        if client.held is not None:
            client.held += data
        else:
            client.outbuf += data
            self._dirty[id(client)] = client
        self._buffered += size
        if self._buffered > self._buffered_peak:
            self._buffered_peak = self._buffered

    def _drop_slow(self, client: _Client, size: int) -> None:
        self._slow_dropped += 1
        self._warn.log(
            logging.ERROR,
            "slow client",
            "client %s is not reading: %d bytes of CAN frames buffered, %d more would exceed "
            "its share of %d bytes (max_buffer_bytes %d / max_clients %d); disconnecting it",
            client.addr,
            client.pending(),
            size,
            self._share,
            self._max_buffer_bytes,
            self._max_clients,
        )
        client.closed = True  # stop queueing; actually closed at the end of the iteration
        self._doomed.append(client)

    def _release_held(self) -> None:
        now = time.monotonic()
        for key, client in list(self._holding.items()):
            if client.hold_until > now:
                continue
            if client.outbuf:
                # The "< ok >" itself has not left yet: keep holding so the frames cannot
                # end up in the same TCP read as the ok.
                client.hold_until = now + self._grace
                continue
            del self._holding[key]
            held, client.held = client.held, None
            if held:
                client.outbuf += held
                self._dirty[id(client)] = client

    def _flush_dirty(self) -> None:
        if not self._dirty:
            return
        dirty = list(self._dirty.values())
        self._dirty.clear()
        for client in dirty:
            if not client.closed:
                self._flush(client)

    def _flush(self, client: _Client) -> None:
        buf = client.outbuf
        while buf:
            try:
                sent = client.sock.send(buf)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                log.info("client %s: send failed (%s); disconnecting", client.addr, exc)
                # Deferred: _flush may run inside the fan-out over a channel's members.
                client.closed = True
                self._doomed.append(client)
                return
            del buf[:sent]
            self._buffered -= sent
        want = bool(buf)
        if want != client.want_write:
            client.want_write = want
            assert self._selector is not None
            events = selectors.EVENT_READ | (selectors.EVENT_WRITE if want else 0)
            self._selector.modify(client.sock, events, client)

    def _disconnect(self, client: _Client, *, quiet: bool = False) -> None:
        if client.sock.fileno() < 0:
            return
        client.closed = True
        self._buffered -= client.pending()
        client.outbuf.clear()
        client.held = None
        fd = client.sock.fileno()
        if self._clients.get(fd) is client:
            del self._clients[fd]
        self._dirty.pop(id(client), None)
        self._holding.pop(id(client), None)
        if client.rawmode and client.channel is not None:
            members = self._channels.get(client.channel, [])
            if client in members:
                members.remove(client)
                self._rawmode_clients -= 1
            if not members:
                self._channels.pop(client.channel, None)
        if self._selector is not None:
            with contextlib.suppress(KeyError, ValueError):
                self._selector.unregister(client.sock)
        client.sock.close()
        if not quiet:
            log.debug("client %s disconnected", client.addr)


class HubProcess:
    """A loopback hub in a child process of its own, so it never waits for its parent's GIL.

    ``python -m hil.bus.loopback --port 0 --exit-with-stdin``: the child prints its port, and
    stops when its standard input (a pipe held by this object) closes, so it cannot outlive a
    parent that is killed. It runs in a session of its own: a Ctrl-C at the terminal reaches
    the parent, which then stops the hub after its own clean-up.

    Parameters
    ----------
    host
        Loopback address to bind.
    timeout
        Seconds to wait for the child to report its port.

    Raises
    ------
    BusError
        The child did not start or did not report a port in time (its last words included).
    """

    def __init__(self, host: str = "127.0.0.1", timeout: float = 10.0) -> None:
        import subprocess

        _check_host(host, allow_remote=False)
        self._process = subprocess.Popen(
            [sys.executable, "-m", "hil.bus.loopback", "--host", host, "--port", "0"]
            + ["--exit-with-stdin"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            start_new_session=True,
        )
        assert self._process.stdout is not None
        ready = selectors.DefaultSelector()
        ready.register(self._process.stdout, selectors.EVENT_READ)
        found = ready.select(timeout)
        ready.close()
        line = self._process.stdout.readline() if found else b""
        match = re.search(rb" on ([0-9.]+):(\d+) ", line)
        if match is None:
            self.stop()
            raise BusError(
                f"the loopback hub process did not start within {timeout:g} s "
                f"(it said {line.decode(errors='replace').strip()!r})"
            )
        self.address = (match[1].decode(), int(match[2]))
        self._process.stdout.close()

    @property
    def port(self) -> int:
        """The hub's TCP port."""
        return self.address[1]

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self._process.pid

    def stop(self, timeout: float = 5.0) -> None:
        """Close the child's standard input (it stops), then wait; SIGKILL after ``timeout`` s.
        Idempotent."""
        import subprocess

        process = self._process
        if process.stdin is not None and not process.stdin.closed:
            with contextlib.suppress(OSError):
                process.stdin.close()
        try:
            process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


_SIZE_SUFFIXES = {"": 1, "K": 1024, "M": 1024**2, "G": 1024**3}


def parse_byte_size(text: str) -> int:
    """Parse ``--max-buffer``: a number of bytes with an optional K, M or G (binary) suffix."""
    match = re.fullmatch(r"\s*(\d+)\s*([KMG]?)(?:i?B)?\s*", text, re.IGNORECASE)
    if not match:
        raise argparse.ArgumentTypeError(f"not a byte size: {text!r} (e.g. 1048576, 512K, 64M)")
    return int(match[1]) * _SIZE_SUFFIXES[match[2].upper()]


def main(argv: list[str] | None = None) -> int:
    """Run a standalone hub until SIGINT/SIGTERM.

    Parameters
    ----------
    argv
        Command line arguments without the program name; ``sys.argv[1:]`` if ``None``.

    Returns
    -------
    int
        Process exit status (0 on a clean shutdown).
    """
    parser = argparse.ArgumentParser(
        prog="python -m hil.bus.loopback",
        description="softhil loopback CAN hub (socketcand protocol, rawmode) over TCP.",
    )
    parser.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    parser.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"TCP port, 0 = any (default {DEFAULT_PORT})"
    )
    parser.add_argument(
        "--allow-remote",
        action="store_true",
        help="permit binding to a non-loopback address (exposes the bus to the network)",
    )
    parser.add_argument(
        "--max-clients",
        type=int,
        default=DEFAULT_MAX_CLIENTS,
        help=f"connections served at once, more are refused (default {DEFAULT_MAX_CLIENTS})",
    )
    parser.add_argument(
        "--max-buffer",
        type=parse_byte_size,
        default=DEFAULT_MAX_BUFFER_BYTES,
        metavar="BYTES",
        help="outgoing bytes buffered for all clients together, e.g. 64M or 512K; each client "
        "may use an equal share and is disconnected when it stops reading beyond it "
        "(default 64M)",
    )
    parser.add_argument(
        "--exit-with-stdin",
        action="store_true",
        help="stop when standard input closes (how a parent process that spawned the hub "
        "takes it down with itself, even if the parent is killed)",
    )
    args = parser.parse_args(argv)
    try:
        return serve(
            args.host,
            args.port,
            allow_remote=args.allow_remote,
            max_clients=args.max_clients,
            max_buffer_bytes=args.max_buffer,
            exit_with_stdin=args.exit_with_stdin,
        )
    except HilError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def serve(
    host: str,
    port: int,
    *,
    allow_remote: bool = False,
    max_clients: int = DEFAULT_MAX_CLIENTS,
    max_buffer_bytes: int = DEFAULT_MAX_BUFFER_BYTES,
    exit_with_stdin: bool = False,
) -> int:
    """Serve a hub in this process until SIGINT/SIGTERM (or, with `exit_with_stdin`, until
    standard input closes); 0 on a clean shutdown. A bad setting or an address that cannot be
    bound raises HilError (`HubSettingError` for a setting) before anything is served."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    hub = LoopbackHub(
        host,
        port,
        allow_remote=allow_remote,
        max_clients=max_clients,
        max_buffer_bytes=max_buffer_bytes,
    )
    hub.bind()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        hub.stop()

    previous: dict[int, Callable[[int, FrameType | None], object] | int | None] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, on_signal)
    if exit_with_stdin:

        def watch_parent() -> None:
            # blocks in read() without the GIL; EOF: the parent closed the pipe or died
            with contextlib.suppress(OSError, ValueError):
                while sys.stdin.buffer.read(4096):
                    pass
            hub.stop()

        threading.Thread(target=watch_parent, name="parent-watch", daemon=True).start()
    try:
        bound_host, bound_port = hub.address
        print(
            f"softhil loopback CAN hub listening on {bound_host}:{bound_port} "
            "(socketcand and softhil binary protocols)",
            flush=True,
        )
        hub.serve_forever()
    finally:
        hub.stop()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
