"""Loopback CAN hub: an inter-process CAN bus over TCP speaking the socketcand protocol.

The kernel softhil runs on has no SocketCAN, so processes share a CAN bus through this hub
instead. It implements the server side of the socketcand ASCII protocol (rawmode only), which
is exactly what python-can's client needs::

    bus = can.Bus(interface="socketcand", channel="sim0", host="127.0.0.1", port=port,
                  tcp_tune=True)

Every frame a client sends on a channel is forwarded to every *other* rawmode client that
opened the same channel (no echo to the sender, like a CAN socket without RECV_OWN_MSGS).

Key invariant: the bus is **ordered, lossless and loopback-only**.

* Ordered: a single-threaded ``selectors`` loop handles all sockets, so every client receives
  the frames of a channel in the one global order in which the hub received them.
* Lossless: frames are never dropped. Each client has an unbounded-in-principle outgoing buffer;
  only if a client stops reading and its buffer exceeds ``max_buffer_bytes`` (64 MiB by
  default) is that client disconnected, with a logged error. It never loses frames silently.
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

Run standalone with ``python -m hil.bus.loopback [--host H] [--port P]``.
"""

from __future__ import annotations

import argparse
import contextlib
import ipaddress
import logging
import re
import selectors
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from types import FrameType, TracebackType
from typing import Self

__all__ = ["DEFAULT_PORT", "LoopbackHub", "main"]

log = logging.getLogger(__name__)

DEFAULT_PORT = 29536
"""Default TCP port of the standalone hub (``python -m hil.bus.loopback``)."""

DEFAULT_MAX_BUFFER_BYTES = 64 * 1024 * 1024
"""Outgoing bytes buffered for one client before it is disconnected as not reading."""

DEFAULT_HANDSHAKE_GRACE = 0.05
"""Seconds frames are held for a client after its rawmode ``< ok >``."""

_RECV_SIZE = 256 * 1024
_MAX_PENDING_INPUT = 4096  # bytes of input without a closing '>' before it is discarded
_MAX_LOGGED_TEXT = 200
_MAX_STD_ID = 0x7FF
_MAX_EXT_ID = 0x1FFFFFFF
_MAX_DLC = 8

_HEX_TOKEN = re.compile(rb"[0-9A-Fa-f]{1,2}")
_HEX_ID = re.compile(rb"[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8}")
_CHANNEL_NAME = re.compile(rb"[!-;=?-~]{1,64}")  # printable ASCII without '<' and '>'


def _check_host(host: str, allow_remote: bool) -> None:
    """Raise ``ValueError`` unless ``host`` is an IPv4 loopback address or remote is allowed.

    Parameters
    ----------
    host
        IPv4 address or host name to bind to.
    allow_remote
        Whether binding to a non-loopback address is permitted.
    """
    try:
        infos = socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise ValueError(f"cannot resolve hub host {host!r} to an IPv4 address: {exc}") from exc
    addresses = {str(info[4][0]) for info in infos}
    if allow_remote:
        return
    remote = sorted(a for a in addresses if not ipaddress.ip_address(a).is_loopback)
    if remote:
        raise ValueError(
            f"refusing to bind the loopback CAN hub to non-loopback address {host!r} "
            f"({', '.join(remote)}): this would expose the CAN bus to the network. "
            "Pass allow_remote=True (CLI: --allow-remote) if that is really intended."
        )


def _shorten(text: bytes) -> str:
    """Return ``text`` as a printable, length-limited string for log messages."""
    s = text.decode("ascii", errors="backslashreplace")
    if len(s) > _MAX_LOGGED_TEXT:
        s = s[:_MAX_LOGGED_TEXT] + f"...({len(s)} chars)"
    return repr(s)


class _Client:
    """State of one TCP connection to the hub."""

    __slots__ = (
        "addr",
        "channel",
        "closed",
        "held",
        "hold_until",
        "inbuf",
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
        self.rawmode = False
        self.want_write = False
        self.closed = False

    def pending(self) -> int:
        """Return the number of outgoing bytes buffered for this client."""
        return len(self.outbuf) + (len(self.held) if self.held is not None else 0)


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
    max_buffer_bytes
        A client whose outgoing buffer exceeds this many bytes (because it stopped reading) is
        disconnected with a logged error.
    handshake_grace
        Seconds to hold frames for a client after its rawmode ``< ok >`` (see module docstring).

    Raises
    ------
    ValueError
        If ``host`` is not a loopback address and ``allow_remote`` is false, or cannot be
        resolved to an IPv4 address.

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
        max_buffer_bytes: int = DEFAULT_MAX_BUFFER_BYTES,
        handshake_grace: float = DEFAULT_HANDSHAKE_GRACE,
    ) -> None:
        _check_host(host, allow_remote)
        if not 0 <= port <= 65535:
            raise ValueError(f"port must be in 0..65535, got {port}")
        if max_buffer_bytes <= 0:
            raise ValueError(f"max_buffer_bytes must be positive, got {max_buffer_bytes}")
        if handshake_grace < 0:
            raise ValueError(f"handshake_grace must be >= 0, got {handshake_grace}")
        self._host = host
        self._requested_port = port
        self._max_buffer_bytes = max_buffer_bytes
        self._grace = handshake_grace
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
        self._clients: dict[int, _Client] = {}  # keyed by socket fd
        self._channels: dict[bytes, list[_Client]] = {}  # rawmode clients per channel
        self._dirty: dict[int, _Client] = {}  # clients with output to flush (insertion order)
        self._holding: dict[int, _Client] = {}  # clients in the handshake grace period
        self._doomed: list[_Client] = []  # clients to disconnect at the end of this iteration
        self._frames_forwarded = 0
        self._rawmode_clients = 0

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
                timeout: float | None = None
                if self._holding:
                    deadline = min(c.hold_until for c in self._holding.values())
                    timeout = max(0.0, deadline - time.monotonic())
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
        except Exception:
            log.exception("loopback CAN hub event loop crashed")
            raise
        finally:
            for client in list(self._clients.values()):
                self._disconnect(client, quiet=True)
            sel.close()
            self._selector = None
            self._close_listener()
            self._done.set()
            log.info("loopback CAN hub stopped")

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
                log.error("loopback CAN hub: accept failed: %s", exc)
                return
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(sock, f"{peer[0]}:{peer[1]}")
            self._clients[sock.fileno()] = client
            self._selector.register(sock, selectors.EVENT_READ, client)
            log.debug("client %s connected", client.addr)
            self._queue(client, b"< hi >")

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
        log.warning("client %s sent malformed input (%s): %s", client.addr, why, _shorten(text))

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
        now = time.time_ns()
        sec, nsec = divmod(now, 1_000_000_000)
        # Same layout as socketcand: "%03X"/"%08X" id, "%ld.%06ld" time, "%02X" per byte.
        frame = b"< frame %s %d.%06d %s >" % (
            id_tok.upper(),
            sec,
            nsec // 1000,
            data.hex().upper().encode(),
        )
        self._frames_forwarded += 1
        for other in self._channels.get(client.channel, ()):
            if other is not client:
                self._queue(other, frame)

    # ------------------------------------------------------------------ output

    def _queue(self, client: _Client, data: bytes) -> None:
        if client.closed:
            return
        if client.held is not None:
            client.held += data
        else:
            client.outbuf += data
            self._dirty[id(client)] = client
        if client.pending() > self._max_buffer_bytes:
            log.error(
                "client %s is not reading: %d bytes of CAN frames buffered (limit %d); "
                "disconnecting it",
                client.addr,
                client.pending(),
                self._max_buffer_bytes,
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
                self._disconnect(client)
                return
            del buf[:sent]
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
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        hub = LoopbackHub(args.host, args.port, allow_remote=args.allow_remote)
        hub.bind()
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    def on_signal(signum: int, frame: FrameType | None) -> None:
        hub.stop()

    previous: dict[int, Callable[[int, FrameType | None], object] | int | None] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, on_signal)
    try:
        host, port = hub.address
        print(
            f"softhil loopback CAN hub listening on {host}:{port} (socketcand protocol)",
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
