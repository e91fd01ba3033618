"""Opening a CAN bus through python-can from a short spec string, the same way on both sides.

Specs:
- `softhil[:[HOST:]PORT][,busy_poll=SECONDS]`: the inter-process hub that `hil` serves on
  127.0.0.1, reached with softhil's binary records (`rigbus.binary`, python-can interface
  `softhil`); what `hil run` gives its plant and controller. `busy_poll`: how long a receive
  polls before it sleeps (`SofthilBus`).
- `loopback[:[HOST:]PORT]`: the same hub, reached with python-can's `socketcand` client (ASCII;
  what tools that know only socketcand use). No kernel CAN support needed for either.
- `virtual[:CHANNEL]`: python-can's in-process bus (one process only).
- `INTERFACE:CHANNEL[,key=value...]`: any python-can interface by name (socketcan:vcan0,
  pcan:PCAN_USBBUS1, kvaser:0, slcan:/dev/ttyACM0,bitrate=1000000, udp_multicast:224.0.0.1...),
  passed through to `can.Bus` with the options given.
- `INTERFACE` alone, or `config`: python-can's own configuration (`can.conf`, the environment
  variables `CAN_INTERFACE`, `CAN_CHANNEL`, `CAN_BITRATE`) fills in what the spec leaves out.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import socket
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import can

DEFAULT_CHANNEL = "softhil"
DEFAULT_LOOPBACK_PORT = 29536
HUB_KINDS = ("softhil", "loopback")  # the hub's two protocols: binary records, socketcand
HUB_OPTIONS = {"softhil": ("busy_poll",), "loopback": ()}  # what each hub client takes
OUR_KINDS = ("loopback", "virtual", "config", "softhil")
KINDS = (*OUR_KINDS, *sorted(can.interfaces.VALID_INTERFACES - set(OUR_KINDS)))


class BusOpenError(ConnectionError):
    """The bus could not be opened; the message names the spec."""


@dataclass(frozen=True)
class BusSpec:
    kind: str = "virtual"  # "softhil", "loopback", "virtual", "config" or a python-can interface
    channel: str | None = DEFAULT_CHANNEL
    host: str = "127.0.0.1"
    port: int = DEFAULT_LOOPBACK_PORT
    options: tuple[tuple[str, str], ...] = field(default=())  # extra can.Bus keyword arguments

    @classmethod
    def parse(cls, text: str) -> BusSpec:
        """Parse a spec (see the module docstring); ValueError naming the spec otherwise."""
        if not text or any(c.isspace() or c in "<>" for c in text):
            raise ValueError(f"bus spec {text!r}: no spaces or '<>' (e.g. loopback:29536)")
        kind, _, rest = text.partition(":")
        if kind == "virtual":
            return cls("virtual", rest or DEFAULT_CHANNEL)
        if kind in HUB_KINDS:
            rest, *pairs = rest.split(",")
            options = _options(text, pairs)
            allowed = HUB_OPTIONS[kind]
            for key, _ in options:
                if key not in allowed:
                    raise ValueError(
                        f"bus spec {text!r}: {kind} takes "
                        + (f"only {', '.join(allowed)}" if allowed else "no options")
                        + f", not {key!r}"
                    )
            host, _, port_text = rest.rpartition(":")
            if not port_text:
                port = DEFAULT_LOOPBACK_PORT
            else:
                try:
                    port = int(port_text)
                except ValueError:
                    raise ValueError(f"bus spec {text!r}: port must be an integer") from None
            if not 1 <= port <= 65535:
                raise ValueError(f"bus spec {text!r}: port must be 1..65535, got {port}")
            return cls(kind, DEFAULT_CHANNEL, host or "127.0.0.1", port, options)
        if kind == "config":
            return cls("config", None)
        if kind not in can.interfaces.VALID_INTERFACES:
            raise ValueError(
                f"bus spec {text!r}: {kind!r} is neither loopback, virtual, config nor a "
                f"python-can interface ({', '.join(KINDS[3:])})"
            )
        channel, *pairs = rest.split(",") if rest else [""]
        return cls(kind, channel or None, options=_options(text, pairs))

    def __str__(self) -> str:
        extra = "".join(f",{k}={v}" for k, v in self.options)
        if self.kind in HUB_KINDS:
            return f"{self.kind}:{self.host}:{self.port}{extra}"
        if self.kind == "config":
            return "config"
        return f"{self.kind}:{self.channel or ''}{extra}"


def _options(text: str, pairs: Sequence[str]) -> tuple[tuple[str, str], ...]:
    """The ``key=value`` options of spec `text`; ValueError naming it otherwise."""
    options = []
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"bus spec {text!r}: options are key=value, got {pair!r}")
        options.append((key, value))
    return tuple(options)


def _option(value: str) -> int | float | bool | str:
    """A spec option as python-can expects it: int, float, bool or text."""
    for convert in (int, float):
        try:
            return convert(value)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(value.lower(), value)


def open_bus(spec: BusSpec, timeout: float = 2.0) -> can.BusABC:
    """A python-can bus for the spec; failures raise BusOpenError naming the spec with a hint.
    A loopback hub that does not answer within `timeout` seconds is an error, not a hang."""
    try:
        if spec.kind == "virtual":
            return can.Bus(interface="virtual", channel=spec.channel, receive_own_messages=False)
        if spec.kind == "softhil":
            # imported here, not through can.Bus(interface="softhil"): the run must not depend
            # on the installed entry point's metadata being current
            from rigbus.binary import SofthilBus

            return SofthilBus(
                f"{spec.host}:{spec.port}",
                bus_name=spec.channel or DEFAULT_CHANNEL,
                connect_timeout=timeout,
                busy_poll=dict(spec.options).get("busy_poll", 0.0),  # the one option it takes
            )
        if spec.kind == "loopback":
            # the client logs a warning each time a TCP read ends inside a frame (not news), and
            # a traceback when the hub goes away (the caller reports that in one line)
            logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.CRITICAL)
            _probe_hub(spec, timeout)
            return can.Bus(
                interface="socketcand",
                channel=spec.channel,
                host=spec.host,
                port=spec.port,
                tcp_tune=True,
            )
        # an interface's own keyword arguments, which python-can takes as Any
        kwargs: dict[str, Any] = {k: _option(v) for k, v in spec.options}
        if spec.kind == "config":
            return can.Bus(**kwargs)  # interface and channel from can.conf / CAN_INTERFACE
        if spec.channel is None:
            return can.Bus(interface=spec.kind, **kwargs)
        return can.Bus(interface=spec.kind, channel=spec.channel, **kwargs)
    except BusOpenError:
        raise  # _probe_hub's, already naming the spec (it is an OSError too)
    except OSError as exc:
        if exc.errno == errno.EAFNOSUPPORT:
            raise BusOpenError(
                f"cannot open CAN bus {spec}: this kernel has no SocketCAN (AF_CAN); use a "
                "loopback hub (hil bus serve, then --bus loopback:HOST:PORT; hil run without "
                "--bus serves its own)"
            ) from exc
        if exc.errno in (errno.ENODEV, errno.ENXIO):
            raise BusOpenError(
                f"cannot open CAN bus {spec}: no interface {spec.channel!r}; create one with "
                f"'hil bus up {spec.channel}' (or ip link add dev {spec.channel} type vcan)"
            ) from exc
        raise BusOpenError(f"cannot open CAN bus {spec}: {exc.strerror or exc}") from exc
    except (can.CanError, TimeoutError, ImportError, ValueError, TypeError) as exc:
        raise BusOpenError(f"cannot open CAN bus {spec}: {exc}") from exc
    except Exception as exc:  # third-party interfaces raise what they like
        raise BusOpenError(f"cannot open CAN bus {spec}: {type(exc).__name__}: {exc}") from exc


def _probe_hub(spec: BusSpec, timeout: float) -> None:
    """Connect, and read the hub's greeting, within `timeout`: python-can's client would wait
    forever for a listener that never greets."""
    try:
        greeting = _greeting(spec.host, spec.port, timeout)
    except socket.gaierror as exc:
        raise BusOpenError(f"cannot open CAN bus {spec}: unknown host {spec.host!r}") from exc
    except ConnectionRefusedError as exc:
        raise BusOpenError(
            f"cannot open CAN bus {spec}: nothing listens on {spec.host}:{spec.port}; start a "
            "hub with 'hil bus serve' (hil run without --bus serves its own)"
        ) from exc
    except TimeoutError as exc:
        raise BusOpenError(
            f"cannot open CAN bus {spec}: {spec.host}:{spec.port} did not greet within "
            f"{timeout:g} s (not a socketcand hub?)"
        ) from exc
    if greeting.startswith(b"< error "):  # the hub refused this client, and says why
        why = greeting.decode("ascii", "replace").removeprefix("< error ").rstrip(" >")
        raise BusOpenError(f"cannot open CAN bus {spec}: the hub refused the connection: {why}")
    if not greeting.startswith(b"< hi >"):
        raise BusOpenError(
            f"cannot open CAN bus {spec}: {spec.host}:{spec.port} is not a socketcand hub "
            f"(it said {greeting[:16]!r})"
        )


def _greeting(host: str, port: int, timeout: float) -> bytes:
    """Connect to a socketcand hub, read its greeting, and leave: half-close, then wait (up to
    `timeout`) for the hub to close its side. Only then has the hub let go of the connection;
    a plain close returned while the hub still counted it, and with `max_clients` reached the
    client that connects next (python-can's, after open_bus's probe) was refused."""
    with socket.create_connection((host, port), timeout=timeout) as sock:
        sock.settimeout(timeout)
        greeting = sock.recv(80)
        with contextlib.suppress(OSError):  # a hub that closed at once, or is slow: go anyway
            sock.shutdown(socket.SHUT_WR)
            deadline = time.monotonic() + timeout
            while sock.recv(4096) and time.monotonic() < deadline:
                pass
        return greeting


def connection_closed(bus: can.BusABC) -> bool:
    """True if the loopback hub under a socketcand bus is gone.

    python-can's socketcand client does not notice a closed connection (its recv returns None
    at once, forever); callers ask this when a receive came back empty, to stop instead of
    spinning. It reads only public state: the hub's address from `channel_info` ("socketcand
    on CHANNEL@HOST:PORT"), probed by a new connection that a live hub greets or refuses."""
    from rigbus.binary import SofthilBus

    if isinstance(bus, SofthilBus):
        return bus.closed  # it knows: a closed connection is a receive of zero bytes
    info = getattr(bus, "channel_info", "")
    if not isinstance(info, str) or not info.startswith("socketcand on "):
        return False
    host, _, port = info.rpartition("@")[2].rpartition(":")
    try:
        # a hub that greets, or refuses (it is at its max_clients, this client among them),
        # is there
        return not _greeting(host, int(port), 1.0).startswith((b"< hi >", b"< error "))
    except (OSError, ValueError):
        return True


def failure_text(exc: BaseException) -> str:
    """A bus failure in one line: python-can's socketcand client puts a whole traceback into
    the text of its CanError; keep what precedes it."""
    text = str(exc).split("Traceback", 1)[0]
    return " ".join(text.split()) or type(exc).__name__


_new = object.__new__


def unchecked_message(
    timestamp: float,
    arbitration_id: int,
    is_extended_id: bool,
    is_remote_frame: bool,
    is_error_frame: bool,
    channel: Any,
    dlc: int,
    data: bytearray,
    is_fd: bool,
    is_rx: bool,
    bitrate_switch: bool,
    error_state_indicator: bool,
) -> can.Message:
    """A `can.Message` with every field given, in a third of the time of its constructor, whose
    checks a message built from another one's fields, or from the DBC codec's bytes, need not
    pass again (the data a bytearray, as the constructor keeps it)."""
    m: can.Message = _new(can.Message)
    m.timestamp = timestamp
    m.arbitration_id = arbitration_id
    m.is_extended_id = is_extended_id
    m.is_remote_frame = is_remote_frame
    m.is_error_frame = is_error_frame
    m.channel = channel
    m.dlc = dlc
    m.data = data
    m.is_fd = is_fd
    m.is_rx = is_rx
    m.bitrate_switch = bitrate_switch
    m.error_state_indicator = error_state_indicator
    return m


def c_messages() -> Any | None:
    """The C codec module (`rigbus.ccodec`) with `can.Message` bound: its
    `data_message(arbitration_id, data, timestamp)` and `copy_message(message, channel)` make
    messages as `unchecked_message` does, filling python-can's slots in place (0.2 us, against
    1 us here); None where the C codec is not in use, or python-can's Message is not made of
    plain slots, and the messages are made in Python."""
    from rigbus import ccodec

    module = ccodec.load()
    if module is None or not module.bind_message(can.Message):
        return None
    return module


def send_all(bus: can.BusABC, messages: Sequence[can.Message]) -> None:
    """Send `messages` in order: in one write on a bus that offers ``send_batch`` (softhil's
    binary records: one system call and one hub wake-up per batch), else one by one. What the
    receivers see, frames and order, is the same either way."""
    batch = getattr(bus, "send_batch", None)
    if batch is not None:
        batch(messages)
        return
    for message in messages:
        bus.send(message)
