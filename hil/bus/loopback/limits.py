"""The loopback hub's limits: its settings and their checks, and the account of what they refused.

`HubLimits` holds the settings that bound what the hub costs (connections, buffered bytes, the
handshake grace, the volume of its warnings) and `check_host` the one that keeps it off the
network; `Accounting` counts what the limits turned away (connections refused, slow clients
dropped, malformed input) and writes the warnings through `RateLimitedLog`.

Key invariant: every setting is checked before the hub binds anything, each failure one line
naming the setting (`HubSettingError`); and however much junk or however many connections
arrive, at most ``log_burst`` warnings of a kind are written per ``log_interval`` seconds.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
from collections.abc import Callable
from dataclasses import dataclass

from hil.errors import BusError

log = logging.getLogger(__package__)  # the hub's one logger, hil.bus.loopback

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

_MAX_LOGGED_TEXT = 200


class HubSettingError(BusError, ValueError):
    """A hub setting (host, port, a limit) is invalid; one line naming the setting.

    Also a ``ValueError``, the type the hub raised for bad settings before there was this class.
    """


def check_host(host: str, allow_remote: bool) -> None:
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


def check_port(port: int) -> None:
    """Raise `HubSettingError` unless ``port`` is a TCP port or 0 (any free port)."""
    if not 0 <= port <= 65535:
        raise HubSettingError(f"hub port must be in 0..65535 (0 = any free port), got {port}")


@dataclass(frozen=True)
class HubLimits:
    """What the hub lets its clients cost; checked on construction (`HubSettingError`).

    Attributes
    ----------
    max_clients
        Connections served at once; further ones get ``< error ... >`` and are closed.
    max_buffer_bytes
        Outgoing bytes buffered for all clients together; each connection may hold `share`.
    handshake_grace
        Seconds frames are held for a client after its rawmode ``< ok >``.
    log_burst, log_interval
        At most ``log_burst`` warnings of one kind per ``log_interval`` seconds.
    """

    max_clients: int = DEFAULT_MAX_CLIENTS
    max_buffer_bytes: int = DEFAULT_MAX_BUFFER_BYTES
    handshake_grace: float = DEFAULT_HANDSHAKE_GRACE
    log_burst: int = DEFAULT_LOG_BURST
    log_interval: float = DEFAULT_LOG_INTERVAL

    def __post_init__(self) -> None:
        if self.max_clients < 1:
            raise HubSettingError(f"max_clients must be at least 1, got {self.max_clients}")
        if self.share < MIN_CLIENT_SHARE:
            raise HubSettingError(
                f"max_buffer_bytes {self.max_buffer_bytes} leaves each of max_clients "
                f"{self.max_clients} clients less than {MIN_CLIENT_SHARE} bytes; "
                f"use at least {MIN_CLIENT_SHARE * self.max_clients}"
            )
        if not self.handshake_grace >= 0:
            raise HubSettingError(f"handshake_grace must be >= 0 s, got {self.handshake_grace}")
        if self.log_burst < 1:
            raise HubSettingError(f"log_burst must be at least 1, got {self.log_burst}")
        if not self.log_interval > 0:
            raise HubSettingError(f"log_interval must be > 0 s, got {self.log_interval}")

    @property
    def share(self) -> int:
        """Outgoing bytes one client may have buffered before it is disconnected."""
        return self.max_buffer_bytes // self.max_clients


class RateLimitedLog:
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


def shorten(text: bytes) -> str:
    """Return ``text`` as a printable, length-limited string for log messages."""
    s = text[:_MAX_LOGGED_TEXT].decode("ascii", errors="backslashreplace")
    if len(text) > _MAX_LOGGED_TEXT:
        s += f"...({len(text)} bytes)"
    return repr(s)


class Accounting:
    """What the limits turned away, counted, each time with a rate-limited warning.

    Parameters
    ----------
    limits
        The hub's limits (named in the warnings).
    clock
        Monotonic seconds, for the warnings' windows.
    """

    def __init__(self, limits: HubLimits, clock: Callable[[], float]) -> None:
        self.limits = limits
        self.warn = RateLimitedLog(log, limits.log_burst, limits.log_interval, clock)
        self.refused = 0
        """Connections refused because ``max_clients`` were connected."""
        self.slow_dropped = 0
        """Clients disconnected because they did not read their frames (share exceeded)."""
        self.malformed = 0
        """Malformed or refused pieces of client input (each one ignored)."""

    def refuse(self, addr: str, connected: int) -> bytes:
        """Count a connection refused at ``max_clients``; the line that tells it why."""
        self.refused += 1
        self.warn.log(
            logging.WARNING,
            "refused connection",
            "loopback CAN hub: refused client %s: %d clients connected (max_clients %d)",
            addr,
            connected,
            self.limits.max_clients,
        )
        return b"< error too many clients (max_clients %d) >" % self.limits.max_clients

    def slow_client(self, addr: str, pending: int, size: int) -> None:
        """Count a client dropped because ``size`` more bytes would exceed its share."""
        self.slow_dropped += 1
        limits = self.limits
        self.warn.log(
            logging.ERROR,
            "slow client",
            "client %s is not reading: %d bytes of CAN frames buffered, %d more would exceed "
            "its share of %d bytes (max_buffer_bytes %d / max_clients %d); disconnecting it",
            addr,
            pending,
            size,
            limits.share,
            limits.max_buffer_bytes,
            limits.max_clients,
        )

    def malformed_input(self, addr: str, text: bytes, why: str) -> None:
        """Count a piece of malformed input ``text`` from ``addr`` (ignored or fatal: ``why``)."""
        self.malformed += 1
        self.warn.log(
            logging.WARNING,
            "malformed input",
            "client %s sent malformed input (%s): %s",
            addr,
            why,
            shorten(text),
        )
