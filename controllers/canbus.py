"""Opening a CAN bus through python-can from a short spec string, the same way on both sides.

Specs: `virtual[:CHANNEL]` (one process), `loopback[:[HOST:]PORT]` (the inter-process hub that
`hil` serves on 127.0.0.1, reached with python-can's socketcand client), `socketcan:IFACE`
(vcan0 or a real adapter, where the kernel has SocketCAN).
"""

from __future__ import annotations

import errno
import logging
import socket
from dataclasses import dataclass

import can

DEFAULT_CHANNEL = "softhil"
DEFAULT_LOOPBACK_PORT = 29536
KINDS = ("virtual", "loopback", "socketcan")


class BusOpenError(ConnectionError):
    """The bus could not be opened; the message names the spec."""


@dataclass(frozen=True)
class BusSpec:
    kind: str = "virtual"
    channel: str = DEFAULT_CHANNEL
    host: str = "127.0.0.1"
    port: int = DEFAULT_LOOPBACK_PORT

    @classmethod
    def parse(cls, text: str) -> BusSpec:
        """Parse `virtual[:CHANNEL]`, `loopback[:[HOST:]PORT]` or `socketcan:IFACE`."""
        kind, _, rest = text.partition(":")
        if kind == "virtual":
            return cls("virtual", rest or DEFAULT_CHANNEL)
        if kind == "loopback":
            host, _, port = rest.rpartition(":")
            try:
                return cls(
                    "loopback",
                    DEFAULT_CHANNEL,
                    host or "127.0.0.1",
                    int(port) if port else DEFAULT_LOOPBACK_PORT,
                )
            except ValueError:
                raise ValueError(f"bus spec {text!r}: port must be an integer") from None
        if kind == "socketcan":
            if not rest:
                raise ValueError(f"bus spec {text!r}: name the interface, e.g. socketcan:vcan0")
            return cls("socketcan", rest)
        raise ValueError(f"bus spec {text!r}: kind must be one of {', '.join(KINDS)}")

    def __str__(self) -> str:
        if self.kind == "loopback":
            return f"loopback:{self.host}:{self.port}"
        return f"{self.kind}:{self.channel}"


def open_bus(spec: BusSpec) -> can.BusABC:
    """A python-can bus for the spec; failures raise BusOpenError naming the spec."""
    try:
        if spec.kind == "virtual":
            return can.Bus(interface="virtual", channel=spec.channel, receive_own_messages=False)
        if spec.kind == "loopback":
            # the client logs a warning each time a TCP read ends inside a frame: not news
            logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)
            return can.Bus(
                interface="socketcand",
                channel=spec.channel,
                host=spec.host,
                port=spec.port,
                tcp_tune=True,
            )
        if spec.kind == "socketcan":
            return can.Bus(interface="socketcan", channel=spec.channel)
    except OSError as exc:
        if spec.kind == "socketcan" and exc.errno == errno.EAFNOSUPPORT:
            raise BusOpenError(
                f"cannot open CAN bus {spec}: this kernel has no SocketCAN (AF_CAN); leave out "
                "--bus and hil run serves its own loopback bus"
            ) from exc
        if spec.kind == "socketcan" and exc.errno in (errno.ENODEV, errno.ENXIO):
            raise BusOpenError(
                f"cannot open CAN bus {spec}: no interface {spec.channel!r}; create one with "
                f"'ip link add dev {spec.channel} type vcan && ip link set up {spec.channel}'"
            ) from exc
        raise BusOpenError(f"cannot open CAN bus {spec}: {exc}") from exc
    except (can.CanError, TimeoutError) as exc:
        raise BusOpenError(f"cannot open CAN bus {spec}: {exc}") from exc
    raise BusOpenError(f"unknown bus kind {spec.kind!r}")


def connection_closed(bus: can.BusABC) -> bool:
    """True if the TCP connection under a loopback (socketcand) bus was closed by the hub.

    python-can's socketcand client does not notice a closed connection: its recv returns None at
    once, forever. Callers ask this when a receive came back empty, to stop instead of spinning.
    """
    sock = getattr(bus, "_SocketCanDaemonBus__socket", None)  # the client's private socket
    if not isinstance(sock, socket.socket):
        return False
    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except BlockingIOError:
        return False
    except OSError:
        return True
