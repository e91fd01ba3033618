"""Tests for hil.bus.loopback: the socketcand-protocol loopback CAN hub.

Everything runs on 127.0.0.1. Waiting is done with receive timeouts, never with sleeps; the
timeouts are generous upper bounds that only matter when something is broken.
"""

from __future__ import annotations

import logging
import os
import random
import re
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import types
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest

from hil.bus.loopback import DEFAULT_PORT, LoopbackHub, fanout, main

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT = 10.0  # upper bound for any single wait; never reached when things work
BusFactory = Callable[..., can.BusABC]

FRAME_RE = re.compile(rb"< frame ([0-9A-F]{3}|[0-9A-F]{8}) (\d+)\.(\d{6}) ([0-9A-F]*) >")


@pytest.fixture(autouse=True)
def _guard_blocking_sockets() -> Iterator[None]:
    """Make blocking sockets (python-can's client has none of its own) time out, not hang.

    Also silences python-can's socketcand client, which logs a warning each time a TCP read
    ends in the middle of a frame (normal under load).
    """
    previous_timeout = socket.getdefaulttimeout()
    socket.setdefaulttimeout(TIMEOUT)
    client_log = logging.getLogger("can.interfaces.socketcand.socketcand")
    previous_level = client_log.level
    client_log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        socket.setdefaulttimeout(previous_timeout)
        client_log.setLevel(previous_level)


@pytest.fixture
def hub() -> Iterator[LoopbackHub]:
    with LoopbackHub() as h:
        yield h


@pytest.fixture
def make_bus(hub: LoopbackHub) -> Iterator[BusFactory]:
    """Factory for python-can socketcand clients of ``hub``; all are shut down afterwards."""
    buses: list[can.BusABC] = []

    def factory(channel: str = "sim0", port: int | None = None) -> can.BusABC:
        bus = can.Bus(
            interface="socketcand",
            channel=channel,
            host="127.0.0.1",
            port=hub.port if port is None else port,
            tcp_tune=True,
        )
        buses.append(bus)
        return bus

    yield factory
    for bus in buses:
        bus.shutdown()


class RawClient:
    """Hand-written socketcand client on a plain TCP socket."""

    def __init__(self, port: int, channel: str | None = None) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.buf = b""
        assert self.read_msg() == b"< hi >"
        if channel is not None:
            self.send(f"< open {channel} >".encode())
            assert self.read_msg() == b"< ok >"
            self.send(b"< rawmode >")
            assert self.read_msg() == b"< ok >"

    @property
    def address(self) -> str:
        host, port = self.sock.getsockname()[:2]
        return f"{host}:{port}"

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def read_msg(self) -> bytes:
        """Return the next ``< ... >`` message (fails on timeout)."""
        while b">" not in self.buf:
            chunk = self.sock.recv(65536)
            assert chunk, "hub closed the connection"
            self.buf += chunk
        end = self.buf.index(b">") + 1
        msg, self.buf = self.buf[:end].strip(), self.buf[end:]
        return msg

    def abort(self) -> None:
        """Close abruptly with a TCP reset."""
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        self.sock.close()

    def close(self) -> None:
        self.sock.close()


def msg(can_id: int, data: bytes | list[int], extended: bool = False) -> can.Message:
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=extended)


def counted(can_id: int, i: int) -> can.Message:
    """Frame whose first four data bytes carry the counter ``i``."""
    return msg(can_id, struct.pack("<IB", i, 0x5A))


def counter(m: can.Message) -> int:
    return struct.unpack_from("<I", m.data)[0]


def recv_n(bus: can.BusABC, n: int) -> list[can.Message]:
    out: list[can.Message] = []
    for _ in range(n):
        m = bus.recv(TIMEOUT)
        assert m is not None, f"timed out after receiving {len(out)} of {n} frames"
        out.append(m)
    return out


def assert_same(received: can.Message, sent: can.Message) -> None:
    assert received.arbitration_id == sent.arbitration_id
    assert received.is_extended_id == sent.is_extended_id
    assert bytes(received.data) == bytes(sent.data)
    assert received.dlc == sent.dlc


def random_frames(rng: random.Random, n: int) -> list[can.Message]:
    special = [0x00, 0x05, 0xFF]
    frames = []
    for k in range(n):
        extended = k % 2 == 1
        can_id = rng.randrange(0x20000000 if extended else 0x800)
        length = k % 8 + 1
        data = [
            rng.choice(special) if rng.random() < 0.5 else rng.randrange(256) for _ in range(length)
        ]
        frames.append(msg(can_id, data, extended))
    frames += [
        msg(0x000, [0x00]),
        msg(0x7FF, [0xFF] * 8),
        msg(0x00000000, [0x05, 0x00, 0xFF], extended=True),
        msg(0x1FFFFFFF, [0x05] * 8, extended=True),
        msg(0x005, [0x00, 0x05, 0xFF, 0x10, 0x01, 0xF0, 0x0F, 0xAB]),
    ]
    return frames


# ---------------------------------------------------------------------------- python-can


def test_two_clients_both_directions(make_bus: BusFactory) -> None:
    a, b = make_bus(), make_bus()
    rng = random.Random(1234)
    frames = random_frames(rng, 64)
    for sender, receiver in ((a, b), (b, a)):
        for f in frames:
            sender.send(f)
        for got, sent in zip(recv_n(receiver, len(frames)), frames, strict=True):
            assert_same(got, sent)
    # Lengths 1..8, both id kinds and the special byte values were really exercised.
    assert {f.dlc for f in frames} == set(range(1, 9))
    assert {f.is_extended_id for f in frames} == {False, True}
    assert {0x00, 0x05, 0xFF} <= {x for f in frames for x in f.data}


def test_order_lossless_and_no_echo_to_sender(hub: LoopbackHub, make_bus: BusFactory) -> None:
    n = 5000
    a, b, c = make_bus(), make_bus(), make_bus()
    for i in range(n):
        a.send(counted(0x123, i))
    for receiver in (b, c):
        assert [counter(m) for m in recv_n(receiver, n)] == list(range(n))
    # b sends a marker only after it saw all of a's frames, so if the hub echoed a's own frames
    # back to a, they would arrive at a before the marker.
    marker = msg(0x7EE, [0xEE])
    b.send(marker)
    assert_same(recv_n(a, 1)[0], marker)
    assert_same(recv_n(c, 1)[0], marker)
    assert hub.frames_forwarded == n + 1
    assert hub.clients == 3


def test_channels_are_isolated(make_bus: BusFactory) -> None:
    a1, a2 = make_bus("a"), make_bus("a")
    b1, b2 = make_bus("b"), make_bus("b")
    on_b = msg(0x0B0, [0xB])
    b1.send(on_b)
    assert_same(recv_n(b2, 1)[0], on_b)
    # The hub handled on_b before on_a, so a leaked on_b would reach a2 first.
    on_a = msg(0x0A0, [0xA])
    a1.send(on_a)
    assert_same(recv_n(a2, 1)[0], on_a)
    on_b2 = msg(0x0B1, [0xB, 1])
    b2.send(on_b2)
    assert_same(recv_n(b1, 1)[0], on_b2)
    on_a2 = msg(0x0A1, [0xA, 1])
    a2.send(on_a2)
    assert_same(recv_n(a1, 1)[0], on_a2)


def test_client_joining_while_traffic_flows(make_bus: BusFactory) -> None:
    sender = make_bus("busy")
    stop = threading.Event()
    errors: list[BaseException] = []

    def pump() -> None:
        i = 0
        try:
            while not stop.is_set():
                sender.send(counted(0x321, i))
                i += 1
        except BaseException as exc:  # noqa: BLE001 - reported by the test thread
            errors.append(exc)

    thread = threading.Thread(target=pump, daemon=True)
    thread.start()
    try:
        for _ in range(15):
            joiner = make_bus("busy")  # handshake must succeed despite the frame stream
            counters = [counter(m) for m in recv_n(joiner, 50)]
            assert counters == list(range(counters[0], counters[0] + 50))
            joiner.shutdown()
    finally:
        stop.set()
        thread.join(TIMEOUT)
    assert not errors


def test_frames_during_handshake_grace_are_held_not_dropped() -> None:
    # A long grace makes it (practically) certain the frames below reach the hub while the
    # joiner is still in its grace period; they must be delivered afterwards, in order.
    with LoopbackHub(handshake_grace=0.2) as hub:
        kwargs = {"interface": "socketcand", "host": "127.0.0.1", "port": hub.port}
        with can.Bus(channel="g", **kwargs) as a, can.Bus(channel="g", **kwargs) as joiner:
            for i in range(100):
                a.send(counted(0x0AB, i))
            assert [counter(m) for m in recv_n(joiner, 100)] == list(range(100))


ECHO_SCRIPT = """
import sys
import can

port, n = int(sys.argv[1]), int(sys.argv[2])
bus = can.Bus(interface="socketcand", channel="echo", host="127.0.0.1", port=port, tcp_tune=True)
bus.send(can.Message(arbitration_id=0x7F0, data=[1], is_extended_id=False))
for _ in range(n):
    m = bus.recv(10.0)
    if m is None:
        sys.exit(3)
    bus.send(can.Message(arbitration_id=m.arbitration_id + 1, data=m.data,
                         is_extended_id=m.is_extended_id))
bus.shutdown()
"""


def test_second_process_echoes_in_order(hub: LoopbackHub, make_bus: BusFactory) -> None:
    n = 1000
    bus = make_bus("echo")
    proc = subprocess.Popen([sys.executable, "-c", ECHO_SCRIPT, str(hub.port), str(n)])
    try:
        ready = recv_n(bus, 1)[0]
        assert ready.arbitration_id == 0x7F0
        sent = []
        for i in range(n):
            extended = i % 3 == 0
            f = msg(0x18FF0000 if extended else 0x100, struct.pack("<I", i), extended)
            sent.append(f)
            bus.send(f)
        for got, f in zip(recv_n(bus, n), sent, strict=True):
            assert got.arbitration_id == f.arbitration_id + 1
            assert got.is_extended_id == f.is_extended_id
            assert bytes(got.data) == bytes(f.data)
        assert proc.wait(TIMEOUT) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# ---------------------------------------------------------------------------- raw protocol


def test_wire_format_and_zero_length_frames(
    hub: LoopbackHub, make_bus: BusFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Fixed hub clock: 1700000000 s + 5 us, to check the "%d.%06d" timestamp layout exactly.
    fake_time = types.SimpleNamespace(
        monotonic=time.monotonic, time_ns=lambda: 1_700_000_000_000_005_999
    )
    monkeypatch.setattr(fanout, "time", fake_time)
    a = make_bus("w")
    raw = RawClient(hub.port, "w")
    try:
        a.send(msg(0x05, [0x00, 0x05, 0xFF]))
        a.send(msg(0xABCDE, [0x0A], extended=True))
        assert raw.read_msg() == b"< frame 005 1700000000.000005 0005FF >"
        assert raw.read_msg() == b"< frame 000ABCDE 1700000000.000005 0A >"
        raw.send(b"< send 7ff 8 ff 0 5 a 10 0 ff 1 >")
        got = recv_n(a, 1)[0]
        assert_same(got, msg(0x7FF, [0xFF, 0, 5, 0xA, 0x10, 0, 0xFF, 1]))
        assert got.timestamp == pytest.approx(1_700_000_000.000005, abs=1e-7)
        # Zero-length frames use socketcand's layout (empty data field) and python-can
        # parses them; softhil itself never sends them.
        a.send(msg(0x042, []))
        assert raw.read_msg() == b"< frame 042 1700000000.000005  >"
        raw.send(b"< send 043 0  >")
        got = recv_n(a, 1)[0]
        assert (got.arbitration_id, bytes(got.data), got.is_extended_id) == (0x43, b"", False)
    finally:
        raw.close()


def test_malformed_input_is_ignored(
    hub: LoopbackHub, make_bus: BusFactory, caplog: pytest.LogCaptureFixture
) -> None:
    a, b = make_bus("m"), make_bus("m")
    raw = RawClient(hub.port, "m")
    garbage = [
        b"hello there ",
        b"< bogus command >",
        b"< >",
        b"< send 12 1 5 >",  # id neither 3 nor 8 digits
        b"< send 123 2 5 >",  # length mismatch
        b"< send 123 9 1 2 3 4 5 6 7 8 9 >",  # too long for classic CAN
        b"< send 123 1 5g >",  # not hex
        b"< send 123 1 0x5 >",
        b"< send 123 1 -1 >",
        b"< send 123 1 100 >",  # byte needs three digits
        b"< send 800 1 5 >",  # standard id out of range
        b"< send 20000000 1 5 >",  # extended id out of range
        b"< send 123 1 \xff\xfe >",  # not ASCII
        b"< open other >",  # already open
        b"< rawmode >",  # already in rawmode
        b"< send 123 1 5 ",  # unterminated, followed by a new message
    ]
    caplog.set_level(logging.WARNING, logger="hil.bus.loopback")
    raw.send(b"".join(garbage))
    # A valid frame split across many TCP writes, then two coalesced into one write.
    valid = b"< send 1AB 3 0 5 ff >"
    for k in range(len(valid)):
        raw.send(valid[k : k + 1])
    raw.send(b"< send 1AC 1 7 >< send 18DAF110 2 ff 0 >")
    expected = [
        msg(0x1AB, [0x00, 0x05, 0xFF]),
        msg(0x1AC, [0x07]),
        msg(0x18DAF110, [0xFF, 0x00], extended=True),
    ]
    for receiver in (a, b):
        for got, sent in zip(recv_n(receiver, 3), expected, strict=True):
            assert_same(got, sent)
    # python-can clients keep working after the garbage.
    a.send(msg(0x200, [1]))
    assert_same(recv_n(b, 1)[0], msg(0x200, [1]))
    assert FRAME_RE.fullmatch(raw.read_msg())
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == len(garbage)
    assert all(raw.address in w for w in warnings)
    assert any("bogus command" in w for w in warnings)
    assert hub.frames_forwarded == 4
    raw.close()


def test_a_nul_from_a_socketcand_client_in_rawmode_is_junk_not_a_binary_hello(
    hub: LoopbackHub, make_bus: BusFactory
) -> None:
    """Only a connection that has not joined yet may start softhil's binary hello (a NUL); from
    a socketcand client in rawmode a NUL is text outside < >, skipped like any other junk."""
    a = make_bus("n")
    raw = RawClient(hub.port, "n")
    try:
        raw.send(b"\0SHB\x01\x01n < send 123 1 5 >")
        assert_same(recv_n(a, 1)[0], msg(0x123, [5]))
        assert hub.malformed_messages == 1
        a.send(msg(0x124, [6]))
        assert raw.read_msg().startswith(b"< frame 124 ")
    finally:
        raw.close()


def test_handshake_errors_are_reported_to_the_client(hub: LoopbackHub) -> None:
    raw = RawClient(hub.port)
    try:
        raw.send(b"< rawmode >")
        assert raw.read_msg().startswith(b"< error ")
        raw.send(b"< send 123 1 5 >")
        assert raw.read_msg().startswith(b"< error ")
        raw.send(b"< open a b >")
        assert raw.read_msg().startswith(b"< error ")
        raw.send(b"< open fine >")
        assert raw.read_msg() == b"< ok >"
    finally:
        raw.close()


def test_abrupt_disconnects_do_not_disturb_others(hub: LoopbackHub, make_bus: BusFactory) -> None:
    a, b = make_bus("d"), make_bus("d")
    victims = [RawClient(hub.port, "d") for _ in range(3)]
    victim_bus = make_bus("d")
    assert hub.clients == 6
    for i in range(100):
        a.send(counted(0x111, i))
    assert [counter(m) for m in recv_n(b, 100)] == list(range(100))
    victims[0].send(b"< send 12")  # half a message, then a reset
    victims[0].abort()
    victims[1].abort()  # unread frames pending in the hub
    victims[2].close()  # orderly close
    victim_bus.shutdown()
    for i in range(100, 200):
        a.send(counted(0x111, i))
    assert [counter(m) for m in recv_n(b, 100)] == list(range(100, 200))
    b.send(msg(0x222, [2]))
    assert_same(recv_n(a, 1)[0], msg(0x222, [2]))
    assert hub.clients == 2


def test_client_that_stops_reading_is_disconnected() -> None:
    with LoopbackHub(max_clients=4, max_buffer_bytes=4 * 1024 * 1024) as hub:
        stalled = socket.socket()
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled.connect(("127.0.0.1", hub.port))
        stalled.sendall(b"< open s >< rawmode >")  # and never read again
        sender, reader = RawClient(hub.port, "s"), RawClient(hub.port, "s")
        try:
            batch = b"".join(
                b"< send 123 8 %x 0 0 0 ff ff ff ff >" % (i % 256) for i in range(2000)
            )
            for _ in range(200):
                sender.send(batch)
                for _ in range(2000):
                    assert FRAME_RE.fullmatch(reader.read_msg())
                if hub.clients == 2:
                    break
            assert hub.clients == 2, "stalled client was never disconnected"
            # The others keep working.
            sender.send(b"< send 7AA 1 aa >")
            assert FRAME_RE.fullmatch(reader.read_msg()).group(1, 4) == (b"7AA", b"AA")
        finally:
            sender.close()
            reader.close()
            stalled.close()


# ---------------------------------------------------------------------------- lifecycle


def test_non_loopback_bind_requires_allow_remote() -> None:
    with pytest.raises(ValueError, match="allow_remote"):
        LoopbackHub("0.0.0.0")
    assert main(["--host", "0.0.0.0", "--port", "0"]) == 2
    LoopbackHub("0.0.0.0", allow_remote=True).stop()  # accepted, never bound
    LoopbackHub("localhost").stop()


def test_stop_is_idempotent() -> None:
    hub = LoopbackHub()
    hub.stop()
    hub.stop()
    hub = LoopbackHub().start()
    port = hub.port
    assert hub.address == ("127.0.0.1", port)
    raw = RawClient(port, "x")
    hub.stop()
    hub.stop()
    assert raw.sock.recv(100) == b""  # the hub closed its client connections
    raw.close()
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT).close()
    with pytest.raises(RuntimeError):
        hub.start()


def test_serve_forever_in_calling_thread_until_stop() -> None:
    hub = LoopbackHub().bind()
    thread = threading.Thread(target=hub.serve_forever)
    thread.start()
    try:
        raw = RawClient(hub.port, "x")  # handshake only succeeds if the hub serves
        raw.close()
    finally:
        hub.stop()
        thread.join(TIMEOUT)
    assert not thread.is_alive()


def test_module_cli_serves_and_exits_on_sigterm(make_bus: BusFactory) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil.bus.loopback", "--port", "0"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None and proc.stderr is not None
        readable, _, _ = select.select([proc.stdout], [], [], TIMEOUT)
        assert readable, "no listening line printed"
        line = proc.stdout.readline()
        match = re.fullmatch(
            r"softhil loopback CAN hub listening on 127\.0\.0\.1:(\d+) "
            r"\(socketcand and softhil binary protocols\)\n",
            line,
        )
        assert match, line
        port = int(match[1])
        assert port not in (0, DEFAULT_PORT)
        a, b = make_bus("cli", port=port), make_bus("cli", port=port)
        a.send(msg(0x1F, [0x00, 0x05, 0xFF]))
        assert_same(recv_n(b, 1)[0], msg(0x1F, [0x00, 0x05, 0xFF]))
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(TIMEOUT) == 0
        assert "Traceback" not in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
