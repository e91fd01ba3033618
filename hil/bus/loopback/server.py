"""The loopback hub's server: the listening socket, the selector loop, the clients, the lifecycle.

`LoopbackHub` binds one TCP port, accepts connections up to ``max_clients``, reads each client's
input and hands it to its protocol's side (`socketcand.SocketcandSide` or `binary.BinarySide`,
told apart by `binary.starts_binary`), whose frames `fanout.Fanout` forwards and buffers; at the
end of every turn of the loop it writes what is queued and closes the clients given up on. It is
served from a thread of its own (`LoopbackHub.start`), the calling thread
(`LoopbackHub.serve_forever`), or its owner's thread, turned by `LoopbackHub.poll` with the
owner as a member of a channel (`LoopbackHub.host`, see `hil.bus.hosted`).

Key invariant: one thread turns the loop, so every client receives the frames of a channel in
the one global order in which the hub received them; `LoopbackHub.stop` may come from any other
thread or a signal handler and only requests the stop, or, for a hosted hub between turns,
closes it at once.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import selectors
import socket
import threading
import time
from collections.abc import Iterable
from types import TracebackType
from typing import Self

from hil.bus.loopback.binary import BinarySide, starts_binary
from hil.bus.loopback.fanout import Fanout
from hil.bus.loopback.limits import (
    DEFAULT_HANDSHAKE_GRACE,
    DEFAULT_LOG_BURST,
    DEFAULT_LOG_INTERVAL,
    DEFAULT_MAX_BUFFER_BYTES,
    DEFAULT_MAX_CLIENTS,
    Accounting,
    HubLimits,
    HubSettingError,
    check_host,
    check_port,
)
from hil.bus.loopback.members import CHANNEL_NAME, Client, HostedMember
from hil.bus.loopback.socketcand import HI, SocketcandSide
from hil.errors import BusError

log = logging.getLogger(__package__)  # the hub's one logger, hil.bus.loopback

_RECV_SIZE = 256 * 1024


def _bind_problem(exc: OSError) -> str:
    """What a failed bind means, in the words a user of ``--host``/``--port`` needs."""
    if exc.errno == errno.EADDRINUSE:
        return "address already in use (another hub or program listens there; choose another port)"
    if exc.errno == errno.EACCES:
        return "permission denied (ports below 1024 need privileges; choose another port)"
    if exc.errno == errno.EADDRNOTAVAIL:
        return "address not available (it is not an address of this machine)"
    return exc.strerror or str(exc)


class LoopbackHub:
    """TCP hub that forwards CAN frames between socketcand (rawmode) and binary clients.

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
        unread frames would exceed its share is disconnected (see `hil.bus.loopback`).
    handshake_grace
        Seconds to hold frames for a client after its rawmode ``< ok >`` (see
        `hil.bus.loopback`).
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
        check_port(port)
        limits = HubLimits(max_clients, max_buffer_bytes, handshake_grace, log_burst, log_interval)
        check_host(host, allow_remote)
        self._host = host
        self._requested_port = port
        self._limits = limits
        self._accounting = Accounting(limits, time.monotonic)
        self._warn = self._accounting.warn
        self._fanout = Fanout(self._accounting, self._watch_write)
        self._socketcand = SocketcandSide(self._fanout, self._accounting)
        self._binary = BinarySide(self._fanout, self._accounting)
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
        self._clients: dict[int, Client] = {}  # keyed by socket fd

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
        return sorted(name.decode() for name in self._fanout.joined)

    @property
    def frames_forwarded(self) -> int:
        """Number of valid frames received from clients and fanned out to their channel.

        Each frame counts once, however many clients (possibly none) it was delivered to.
        """
        return self._fanout.frames_forwarded

    @property
    def clients(self) -> int:
        """Number of currently connected clients in rawmode."""
        return self._fanout.rawmode_clients

    @property
    def max_client_buffer(self) -> int:
        """Outgoing bytes one client may have buffered before it is disconnected."""
        return self._limits.share

    @property
    def buffered_bytes(self) -> int:
        """Outgoing bytes the hub holds right now for all clients (at most ``max_buffer_bytes``)."""
        return self._fanout.buffered

    @property
    def buffered_bytes_peak(self) -> int:
        """The highest :attr:`buffered_bytes` so far."""
        return self._fanout.buffered_peak

    @property
    def slow_clients_dropped(self) -> int:
        """Clients disconnected because they did not read their frames (share exceeded)."""
        return self._accounting.slow_dropped

    @property
    def clients_refused(self) -> int:
        """Connections refused because ``max_clients`` were connected."""
        return self._accounting.refused

    @property
    def malformed_messages(self) -> int:
        """Malformed or refused pieces of client input (each one ignored)."""
        return self._accounting.malformed

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

    def _open_selector(self) -> selectors.BaseSelector:
        """The loop's selector, watching the listener and the wake-up socket."""
        assert self._listener is not None and self._wake_r is not None
        sel = selectors.DefaultSelector()
        sel.register(self._listener, selectors.EVENT_READ, None)
        sel.register(self._wake_r, selectors.EVENT_READ, None)
        self._selector = sel
        return sel

    # ------------------------------------------------------------------ event loop

    def _run(self) -> None:
        self._loop_ident = threading.get_ident()
        try:
            if self._listener is None or self._wake_r is None:  # stop() won a race with start()
                return
            self._open_selector()
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
        due = self._warn.next_deadline()
        release = self._fanout.release_due()
        if release is not None and (due is None or release < due):
            due = release
        return None if due is None else max(0.0, due - time.monotonic())

    def _turn(self, timeout: float | None) -> None:
        """One turn of the event loop: wait at most `timeout` [s] for sockets to be ready,
        serve them, release held clients, write what is queued, drop the doomed."""
        sel, listener, wake_r, fanout = self._selector, self._listener, self._wake_r, self._fanout
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
                    fanout.dirty[id(client)] = client
        if fanout.holding:
            fanout.release_held()
        self._write_out()
        if summary_due is not None:
            self._warn.flush()

    def _write_out(self) -> None:
        """Write what is queued, then close the clients given up on meanwhile."""
        fanout = self._fanout
        fanout.flush_dirty()
        for client in fanout.doomed:
            self._disconnect(client)
        fanout.doomed.clear()

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

    def host(self, channel: str) -> HostedMember:
        """Serve from the calling thread, turned by `poll` (no thread of its own), with the
        caller as a member of `channel`: what other members send it waits in the returned
        member's `inbox`, what it sends goes out through `send_from`. Close with `stop`."""
        name = channel.encode()
        if not CHANNEL_NAME.fullmatch(name):
            raise HubSettingError(f"invalid channel name {channel!r}")
        self.bind()
        with self._lock:
            self._claim_start()
            self._loop_ident = threading.get_ident()
            self._hosted = True
        self._open_selector()
        member = HostedMember(name)
        self._fanout.host(member)
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

    def send_from(self, member: HostedMember, frames: Iterable[tuple[int, bool, bytes]]) -> None:
        """Forward frames (id, extended, data) from a hosted member to the rest of its
        channel, in order, and write them out now (what a socket does not take yet stays
        queued for the next turns)."""
        if self._selector is None:
            raise BusError("the hosted hub is closed")
        forward = self._fanout.forward
        for can_id, extended, data in frames:
            forward(member, can_id, extended, data)
        self._write_out()

    # ------------------------------------------------------------------ clients

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
            if len(self._clients) >= self._limits.max_clients:
                self._refuse(sock, addr)
                continue
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = Client(sock, addr)
            self._clients[sock.fileno()] = client
            self._selector.register(sock, selectors.EVENT_READ, client)
            log.debug("client %s connected", client.addr)
            self._fanout.queue(client, HI)

    def _refuse(self, sock: socket.socket, addr: str) -> None:
        """Tell a connection beyond ``max_clients`` why it is closed, then close it."""
        reason = self._accounting.refuse(addr, len(self._clients))
        # Best effort and non-blocking: python-can reports this text as its handshake failure.
        with contextlib.suppress(OSError):
            sock.send(reason)
        sock.close()

    def _on_readable(self, client: Client) -> None:
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
        client.inbuf += data
        if starts_binary(client):
            self._binary.on_input(client)
        else:
            self._socketcand.on_input(client)

    def _watch_write(self, client: Client, want: bool) -> None:
        """Watch ``client``'s socket for writing while it has output the kernel did not take."""
        assert self._selector is not None
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if want else 0)
        self._selector.modify(client.sock, events, client)

    def _disconnect(self, client: Client, *, quiet: bool = False) -> None:
        if client.sock.fileno() < 0:
            return
        client.closed = True
        fd = client.sock.fileno()
        if self._clients.get(fd) is client:
            del self._clients[fd]
        self._fanout.leave(client)
        if self._selector is not None:
            with contextlib.suppress(KeyError, ValueError):
                self._selector.unregister(client.sock)
        client.sock.close()
        if not quiet:
            log.debug("client %s disconnected", client.addr)
