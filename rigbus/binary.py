"""softhil's binary CAN transport: length-prefixed records to the loopback hub, as a python-can bus.

The loopback hub (`hil.bus.loopback`) speaks two protocols on one TCP port: socketcand's ASCII
for tools that only know that, and this binary one for softhil's own plant and controller.
Every frame is forwarded to every other client of the same hub channel, whatever its protocol.
python-can reaches it through its ``can.interface`` entry point::

    bus = can.Bus(interface="softhil", channel="127.0.0.1:29536")
    python -m can.logger -i softhil -c 127.0.0.1:29536 -f run.log

Wire format (all integers little-endian). The hub greets every connection with socketcand's
``< hi >``; a binary client answers with a hello instead of ``< open NAME >``::

    client -> hub   00 'S' 'H' 'B' VERSION LEN NAME[LEN]    join hub channel NAME
    hub -> client   00 'S' 'H' 'B' VERSION 00               joined (or "< error ... >", closed)

then, in both directions, one record per CAN frame (`RECORD`)::

    u16 size      bytes after this field: 14 + dlc
    u32 id        11-bit or 29-bit arbitration id
    u8  flags     bit 0: extended id (no other flag is defined)
    u8  dlc       0..8 data bytes
    f64 time      seconds; the hub stamps its receive time (time.time()), as socketcand does
    u8  data[dlc]

Key invariant: a record is never split or merged by the client: `SofthilBus.send` writes one
whole record with one ``sendall`` and `SofthilBus.recv` returns exactly the records the hub sent,
in its order; a malformed record from the hub is a protocol error, never skipped, because a
length-prefixed stream cannot be resynchronised.
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import socket
import time
from collections.abc import Sequence
from typing import Any

import can

from rigbus.wire import (
    DEFAULT_PORT,
    FLAG_EXTENDED,
    GREETING,
    HEADER,
    MAX_DLC,
    MAX_EXT_ID,
    MAX_STD_ID,
    SIZE_FIELD,
    ack,
    encode_record,
    hello,
)

__all__ = ["SofthilBus", "busy_poll_seconds", "classic_data", "parse_channel"]

_RECV_SIZE = 256 * 1024


def classic_data(msg: can.Message) -> bytes:
    """The data of a classic CAN data frame, the only frames softhil's transport carries;
    CanOperationError for a remote, error or FD frame, more than 8 bytes or an id out of range."""
    if msg.is_remote_frame or msg.is_error_frame or msg.is_fd:
        raise can.CanOperationError(
            f"softhil bus: only classic data frames are carried, not 0x{msg.arbitration_id:X}"
            f" ({'remote' if msg.is_remote_frame else 'error' if msg.is_error_frame else 'FD'})"
        )
    data = bytes(msg.data)
    can_id = msg.arbitration_id
    if len(data) > MAX_DLC or can_id > (MAX_EXT_ID if msg.is_extended_id else MAX_STD_ID):
        raise can.CanOperationError(
            f"softhil bus: frame 0x{can_id:X} has {len(data)} bytes or an id out of range"
        )
    return data


MAX_BUSY_POLL = 1.0  # [s] a budget beyond a second is a mistake (it would be one core lost)


def busy_poll_seconds(value: object) -> float:
    """A receive's busy-poll budget [s] (see `SofthilBus`): a number, or text such as
    ``"0.002"``, in 0..MAX_BUSY_POLL; ValueError naming it otherwise."""
    try:
        seconds = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        seconds = math.nan
    if not 0.0 <= seconds <= MAX_BUSY_POLL:  # also NaN
        raise ValueError(
            f"softhil busy_poll {value!r}: expected seconds in 0..{MAX_BUSY_POLL:g} (e.g. 0.002)"
        )
    return seconds


def parse_channel(channel: object) -> tuple[str, int]:
    """``"HOST:PORT"``, ``"PORT"`` or ``":PORT"`` as ``(host, port)``; host 127.0.0.1 by default.

    Raises
    ------
    ValueError
        Naming the channel, if the port is not an integer in 1..65535.
    """
    text = str(channel if channel is not None else DEFAULT_PORT)
    host, _, port_text = text.rpartition(":")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(
            f"softhil channel {text!r}: expected HOST:PORT (e.g. 127.0.0.1:{DEFAULT_PORT})"
        ) from None
    if not 1 <= port <= 65535:
        raise ValueError(f"softhil channel {text!r}: port must be 1..65535, got {port}")
    return host or "127.0.0.1", port


def _read_exactly(sock: socket.socket, n: int, what: str) -> bytes:
    """``n`` bytes from a socket with a timeout set, or a whole ``< error ... >`` line that the
    hub sends instead; CanInitializationError if the connection closes first."""
    data = b""
    while len(data) < n or (data.startswith(b"< err") and b">" not in data[:256]):
        chunk = sock.recv(max(1, n - len(data)))
        if not chunk:
            if data.startswith(b"< err"):
                break
            raise can.CanInitializationError(f"the hub closed the connection during {what}")
        data += chunk
    return data


def _refusal(answer: bytes) -> str | None:
    """The reason in a hub's ``< error REASON >``, or None."""
    if not answer.startswith(b"< error"):
        return None
    return answer[len(b"< error") :].partition(b">")[0].decode("ascii", "replace").strip()


class SofthilBus(can.BusABC):
    """A python-can bus on the softhil loopback hub, speaking its binary records.

    Parameters
    ----------
    channel
        ``"HOST:PORT"`` of the hub (``hil bus serve`` listens on 127.0.0.1:29536).
    bus_name
        The hub channel to join (socketcand clients name it in ``< open NAME >``); the
        default is softhil's own, ``"softhil"``.
    connect_timeout
        Seconds to connect and complete the handshake before `can.CanInitializationError`.
    can_filters
        python-can's filters, applied in software.
    busy_poll
        Seconds a receive polls the socket without sleeping before it waits in ``select``
        (0, the default: it sleeps at once). Waking a sleeping process costs from tens to
        hundreds of microseconds, more on a virtual machine; a peer that answers within the
        budget is read as soon as its frames land. Worth it only with a core to spare: it
        burns its own core for up to that long per receive (`hil run` sets it for its
        controller when the plant hosts the hub on a machine with two cores or more).
    **kwargs
        Passed to `can.BusABC`.

    Raises
    ------
    can.CanInitializationError
        Nothing listens, the listener is not a softhil hub, or the hub refused the client
        (its reason, e.g. ``too many clients``, is in the message); a `busy_poll` that is not
        a number of seconds in 0..1.
    """

    def __init__(
        self,
        channel: object = f"127.0.0.1:{DEFAULT_PORT}",
        bus_name: str = "softhil",
        connect_timeout: float = 2.0,
        can_filters: can.typechecking.CanFilters | None = None,
        busy_poll: float | str = 0.0,
        **kwargs: Any,
    ) -> None:
        try:
            host, port = parse_channel(channel)
            self._busy_poll = busy_poll_seconds(busy_poll)
        except ValueError as exc:
            raise can.CanInitializationError(str(exc)) from None
        where = f"{host}:{port}"
        try:
            raw = bus_name.encode("ascii")
        except UnicodeEncodeError:
            raw = b""
        if not 1 <= len(raw) <= 64 or any(c <= 0x20 or c in b"<>" or c > 0x7E for c in raw):
            raise can.CanInitializationError(
                f"softhil bus_name {bus_name!r}: 1..64 printable ASCII, no spaces or '<>'"
            )
        try:
            sock = socket.create_connection((host, port), timeout=connect_timeout)
        except OSError as exc:
            raise can.CanInitializationError(
                f"cannot reach the softhil hub at {where}: {exc.strerror or exc}"
            ) from None
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            greeting = _read_exactly(sock, len(GREETING), "the greeting")
            reason = _refusal(greeting)
            if reason is not None:
                raise can.CanInitializationError(f"the hub at {where} refused: {reason}")
            if greeting != GREETING:
                raise can.CanInitializationError(
                    f"{where} is not a softhil hub (it said {greeting[:40]!r})"
                )
            sock.sendall(hello(bus_name))
            answer = _read_exactly(sock, len(ack()), "the binary hello")
            if answer != ack():
                raise can.CanInitializationError(
                    f"the hub at {where} refused the binary client: "
                    f"{_refusal(answer) or answer.decode('ascii', 'replace')}"
                )
            sock.settimeout(None)  # blocking sends; receives poll first (see _recv_internal)
        except TimeoutError:
            sock.close()
            raise can.CanInitializationError(
                f"the hub at {where} did not answer within {connect_timeout:g} s"
            ) from None
        except can.CanInitializationError:
            sock.close()
            raise
        except OSError as exc:
            sock.close()
            raise can.CanInitializationError(
                f"the hub at {where} failed the handshake: {exc.strerror or exc}"
            ) from None
        self._sock = sock
        self._buf = bytearray()
        self._pos = 0  # parse position in _buf: consumed bytes are dropped in batches
        self._closed = False
        self._where = where
        self.channel_info = f"softhil binary on {bus_name}@{where}"
        super().__init__(channel=where, can_filters=can_filters, **kwargs)

    @property
    def busy_poll(self) -> float:
        """Seconds a receive polls before it sleeps (0: at once)."""
        return self._busy_poll

    @property
    def closed(self) -> bool:
        """Whether the hub closed the connection (or the bus was shut down)."""
        return self._closed

    def fileno(self) -> int:
        """The socket's descriptor, for `can.Notifier`'s selector."""
        return self._sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one classic data frame as one record (``timeout`` is not used: loopback TCP
        with a hub that reads everything; a stalled hub surfaces as a closed connection)."""
        self._write(self._record(msg))

    def send_batch(self, messages: Sequence[can.Message]) -> None:
        """Send frames in order as consecutive records in one write: one system call and one
        wake-up of the hub instead of one per frame (the hub forwards what it reads in one go,
        so the receiver gets them in one read too). Receivers see the same frames in the same
        order as from `send` one by one; nothing is sent if any frame is invalid."""
        self._write(b"".join([self._record(msg) for msg in messages]))

    @staticmethod
    def _record(msg: can.Message) -> bytes:
        return encode_record(
            msg.arbitration_id, msg.is_extended_id, classic_data(msg), msg.timestamp
        )

    def _write(self, records: bytes) -> None:
        try:
            self._sock.sendall(records)
        except OSError as exc:
            self._closed = True
            raise can.CanOperationError(f"softhil bus: send failed: {exc}") from None

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        message = self._next()
        if message is not None:
            return message, False
        now = time.monotonic()
        deadline = None if timeout is None else now + timeout
        busy_until = now + self._busy_poll  # see busy_poll: no select before then
        while True:
            try:
                data = self._sock.recv(_RECV_SIZE, socket.MSG_DONTWAIT)
            except BlockingIOError:
                now = time.monotonic()
                remaining = None if deadline is None else deadline - now
                if remaining is not None and remaining <= 0:
                    return None, False
                if now < busy_until:
                    os.sched_yield()  # a process that this one waits for may need the core
                    continue
                ready, _, _ = select.select([self._sock], [], [], remaining)
                if not ready:
                    return None, False
                continue
            except InterruptedError:
                continue
            except OSError as exc:
                self._closed = True
                raise can.CanOperationError(f"softhil bus: receive failed: {exc}") from None
            if not data:
                self._closed = True
                raise can.CanOperationError("softhil bus: the hub closed the connection")
            self._buf += data
            message = self._next()
            if message is not None:
                return message, False

    def _next(self) -> can.Message | None:
        """The next whole record in the buffer as a message, or None."""
        buf, pos = self._buf, self._pos
        if len(buf) - pos < HEADER.size:
            self._compact()
            return None
        size, can_id, flags, dlc, stamp = HEADER.unpack_from(buf, pos)
        end = pos + SIZE_FIELD + size
        if size != HEADER.size - SIZE_FIELD + dlc or dlc > MAX_DLC or flags & ~FLAG_EXTENDED:
            self._closed = True
            raise can.CanOperationError(
                f"softhil bus: malformed record from the hub (size {size}, dlc {dlc}, "
                f"flags 0x{flags:02X})"
            )
        if len(buf) < end:
            self._compact()
            return None
        self._pos = end
        return can.Message(
            timestamp=stamp,
            arbitration_id=can_id,
            is_extended_id=bool(flags & FLAG_EXTENDED),
            dlc=dlc,
            data=buf[end - dlc : end],
            channel=self._where,
            check=False,
        )

    def _compact(self) -> None:
        if self._pos:
            del self._buf[: self._pos]
            self._pos = 0

    def shutdown(self) -> None:
        """Close the connection to the hub. Idempotent."""
        if not self._is_shutdown:
            self._closed = True
            with contextlib.suppress(OSError):
                self._sock.close()
        super().shutdown()

    @staticmethod
    def _detect_available_configs() -> list[can.typechecking.AutoDetectedConfig]:
        """The default hub's channel if a softhil hub greets there within 0.2 s."""
        try:
            with socket.create_connection(("127.0.0.1", DEFAULT_PORT), timeout=0.2) as sock:
                sock.settimeout(0.2)
                if sock.recv(len(GREETING)) != GREETING:
                    return []
        except OSError:
            return []
        return [{"interface": "softhil", "channel": f"127.0.0.1:{DEFAULT_PORT}"}]
