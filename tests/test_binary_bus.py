"""softhil's binary CAN transport (rigbus.binary) on the loopback hub beside socketcand.

Laws under test: every frame reaches every *other* member of its hub channel whatever protocol
each speaks, in the hub's order, unchanged (id, extended flag, data); records are exactly the
documented wire format; malformed binary input costs its sender the connection, never the
others; the hub's limits count binary clients alike; python-can reaches the bus through its
``can.interface`` entry point and CLIs. Everything runs on 127.0.0.1; waits are receive timeouts,
never sleeps, and nothing asserts on time.
"""

from __future__ import annotations

import os
import random
import re
import signal
import socket
import subprocess
import sys
import threading
import tomllib
from collections.abc import Iterator
from importlib import import_module
from pathlib import Path

import can
import pytest

from hil.bus.loopback import HubProcess, LoopbackHub
from rigbus import wire
from rigbus.binary import SofthilBus, parse_channel
from rigbus.canbus import BusSpec, connection_closed, open_bus, send_all
from tests.helpers import blocking_sockets_time_out, interruptible

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT = 10.0  # upper bound of any single wait; never reached when things work


@pytest.fixture(autouse=True)
def _guard_blocking_sockets() -> Iterator[None]:
    with blocking_sockets_time_out(TIMEOUT):
        yield


@pytest.fixture
def hub() -> Iterator[LoopbackHub]:
    with LoopbackHub(handshake_grace=0.0) as h:
        yield h


@pytest.fixture
def buses(hub: LoopbackHub) -> Iterator[list[can.BusABC]]:
    """Buses opened by a test, shut down after it."""
    opened: list[can.BusABC] = []
    yield opened
    for bus in opened:
        bus.shutdown()


def binary(hub: LoopbackHub, opened: list[can.BusABC], name: str = "softhil") -> SofthilBus:
    bus = SofthilBus(f"127.0.0.1:{hub.port}", bus_name=name)
    opened.append(bus)
    return bus


def ascii_bus(hub: LoopbackHub, opened: list[can.BusABC], name: str = "softhil") -> can.BusABC:
    bus = can.Bus(interface="socketcand", channel=name, host="127.0.0.1", port=hub.port)
    opened.append(bus)
    return bus


def joined(hub: LoopbackHub, n: int) -> None:
    """Wait (by polling the hub's counter, bounded) until ``n`` clients joined a channel."""
    for _ in range(100_000):
        if hub.clients >= n:
            return
        socket.socket().close()  # a syscall: lets the hub thread run without a sleep
    raise AssertionError(f"only {hub.clients} of {n} clients joined")


def frames(rng: random.Random, n: int) -> list[can.Message]:
    """Random classic data frames: both id kinds, every length 0..8."""
    out = []
    for i in range(n):
        extended = rng.random() < 0.5
        can_id = rng.randrange(0x20000000 if extended else 0x800)
        data = bytes(rng.randrange(256) for _ in range(i % 9))
        out.append(can.Message(arbitration_id=can_id, is_extended_id=extended, data=data))
    return out


def same(received: can.Message | None, sent: can.Message) -> None:
    assert received is not None, f"frame 0x{sent.arbitration_id:X} was not received"
    assert received.arbitration_id == sent.arbitration_id
    assert received.is_extended_id == sent.is_extended_id
    assert bytes(received.data) == bytes(sent.data)
    assert received.dlc == len(sent.data)


def test_every_frame_reaches_every_other_client_in_both_protocols(
    hub: LoopbackHub, buses: list[can.BusABC]
) -> None:
    a, b = binary(hub, buses), binary(hub, buses)
    t = ascii_bus(hub, buses)
    joined(hub, 3)
    sent = frames(random.Random(1), 60)
    for i, message in enumerate(sent):
        sender = (a, b, t)[i % 3]
        sender.send(message)
        for receiver in (a, b, t):
            if receiver is not sender:
                same(receiver.recv(TIMEOUT), message)
    for bus in (a, b, t):  # no echo to the sender, nothing left over
        assert bus.recv(0.05) is None
    assert hub.frames_forwarded == len(sent)


def test_order_is_kept_across_protocols_for_a_burst(
    hub: LoopbackHub, buses: list[can.BusABC]
) -> None:
    a, b, t = binary(hub, buses), binary(hub, buses), ascii_bus(hub, buses)
    joined(hub, 3)
    sent = [
        can.Message(arbitration_id=0x181, is_extended_id=False, data=i.to_bytes(4, "big"))
        for i in range(3000)
    ]
    for message in sent:
        a.send(message)
    for receiver in (b, t):
        got = [int.from_bytes(receiver.recv(TIMEOUT).data, "big") for _ in sent]
        assert got == list(range(len(sent)))


def test_channels_are_isolated_for_binary_clients(
    hub: LoopbackHub, buses: list[can.BusABC]
) -> None:
    a, b, other = binary(hub, buses, "x"), ascii_bus(hub, buses, "x"), binary(hub, buses, "y")
    joined(hub, 3)
    a.send(can.Message(arbitration_id=0x80, is_extended_id=False, data=b"\x01"))
    same(b.recv(TIMEOUT), can.Message(arbitration_id=0x80, is_extended_id=False, data=b"\x01"))
    assert other.recv(0.05) is None


def test_records_are_the_documented_wire_format(hub: LoopbackHub, buses: list[can.BusABC]) -> None:
    raw = socket.create_connection(("127.0.0.1", hub.port), timeout=TIMEOUT)
    try:
        assert raw.recv(6) == b"< hi >"
        raw.sendall(b"\x00SHB\x01\x07softhil")
        assert raw.recv(6) == b"\x00SHB\x01\x00"
        t = ascii_bus(hub, buses)
        joined(hub, 2)
        # a record written by hand: size 14 + 3, id 0x18FF1234 extended, dlc 3, time ignored
        raw.sendall(bytes.fromhex("11003412ff180103") + bytes(8) + b"\xaa\xbb\xcc")
        same(
            t.recv(TIMEOUT),
            can.Message(arbitration_id=0x18FF1234, is_extended_id=True, data=b"\xaa\xbb\xcc"),
        )
        t.send(can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x05"))
        record = b""
        while len(record) < 17:
            record += raw.recv(17 - len(record))
        size, can_id, flags, dlc, stamp = wire.HEADER.unpack_from(record)
        assert (size, can_id, flags, dlc, record[16:]) == (15, 0x123, 0, 1, b"\x05")
        assert stamp > 1e9  # the hub's receive time, seconds since the epoch, as socketcand
        # a binary sender's frames reach a socketcand client in socketcand's own text
        text = socket.create_connection(("127.0.0.1", hub.port), timeout=TIMEOUT)
        text.sendall(b"< open softhil >< rawmode >")
        received = b""
        while received.count(b">") < 3:
            received += text.recv(100)
        assert received == b"< hi >< ok >< ok >"
        joined(hub, 3)
        raw.sendall(wire.encode_record(0x1ABCDE, True, b"\x01\xff", 0.0))
        raw.sendall(wire.encode_record(0x0F, False, b"", 0.0))
        received = b""
        while received.count(b">") < 2:
            received += text.recv(200)
        text.close()
        first, second = (line.split() for line in received.split(b">")[:2])
        assert first[:3] == [b"<", b"frame", b"001ABCDE"] and first[4:] == [b"01FF"]
        assert second[:3] == [b"<", b"frame", b"00F"] and len(second) == 4  # no data field
    finally:
        raw.close()


@pytest.mark.parametrize(
    ("bad", "why"),
    [
        (bytes.fromhex("1200230100000003") + bytes(11), "bad record"),  # size != 14+dlc
        (bytes.fromhex("1700230100000009") + bytes(17), "bad record"),  # dlc 9, size 14+9
        (bytes.fromhex("0e00000800000000") + bytes(8), "bad record"),  # std id 0x800
        (bytes.fromhex("0e00230100000200") + bytes(8), "bad record"),  # unknown flag
    ],
)
def test_a_malformed_record_disconnects_its_sender_only(
    hub: LoopbackHub,
    buses: list[can.BusABC],
    bad: bytes,
    why: str,
    caplog: pytest.LogCaptureFixture,
) -> None:
    good, t = binary(hub, buses), ascii_bus(hub, buses)
    raw = socket.create_connection(("127.0.0.1", hub.port), timeout=TIMEOUT)
    try:
        assert raw.recv(6) == b"< hi >"
        raw.sendall(b"\x00SHB\x01\x07softhil")
        assert raw.recv(6) == b"\x00SHB\x01\x00"
        joined(hub, 3)
        raw.sendall(bad)
        assert raw.recv(100) == b""  # closed by the hub
    finally:
        raw.close()
    assert hub.malformed_messages == 1
    assert any(why in r.getMessage() for r in caplog.records)
    message = can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"\x01\x02")
    good.send(message)
    same(t.recv(TIMEOUT), message)


@pytest.mark.parametrize(
    ("hello", "reason"),
    [
        (b"\x00SHB\x02\x07softhil", "binary protocol version 2 unsupported"),
        (b"\x00SHB\x01\x03a b", "invalid channel name"),
        (b"\x00XYZ\x01\x01a", "not a binary hello"),
    ],
)
def test_a_bad_hello_is_refused_with_its_reason(
    hub: LoopbackHub, hello: bytes, reason: str
) -> None:
    raw = socket.create_connection(("127.0.0.1", hub.port), timeout=TIMEOUT)
    try:
        assert raw.recv(6) == b"< hi >"
        raw.sendall(hello)
        answer = b""
        while chunk := raw.recv(200):
            answer += chunk
        assert answer == b"< error " + reason.encode() + b" >"
    finally:
        raw.close()
    assert hub.clients == 0


def test_max_clients_counts_binary_clients() -> None:
    with LoopbackHub(max_clients=2, max_buffer_bytes=2 * 65536) as hub:
        first = SofthilBus(f"127.0.0.1:{hub.port}")
        second = can.Bus(interface="socketcand", channel="softhil", host="127.0.0.1", port=hub.port)
        try:
            with pytest.raises(can.CanInitializationError, match="too many clients"):
                SofthilBus(f"127.0.0.1:{hub.port}")
            assert hub.clients_refused == 1
        finally:
            first.shutdown()
            second.shutdown()


def test_a_binary_client_that_stops_reading_is_disconnected() -> None:
    with LoopbackHub(max_clients=4, max_buffer_bytes=4 * 65536) as hub:
        clients = []
        for rcvbuf in (4096, None, None):
            sock = socket.socket()
            if rcvbuf:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
            sock.settimeout(TIMEOUT)
            sock.connect(("127.0.0.1", hub.port))
            sock.sendall(b"\x00SHB\x01\x07softhil")
            clients.append(sock)
        stalled, sender, reader = clients  # the stalled one joins, then never reads again
        try:
            joined(hub, 3)
            record = wire.encode_record(0x181, False, bytes(8), 0.0)
            batch = record * 20_000
            pending = 12  # the reader's greeting and ack (the sender's are never read)
            for _ in range(100):
                sender.sendall(batch)
                pending += len(batch)
                while pending > 0:
                    pending -= len(reader.recv(1 << 20))
                if hub.clients == 2:
                    break
            assert hub.clients == 2, "the stalled binary client was never disconnected"
            assert hub.slow_clients_dropped == 1
            assert hub.buffered_bytes_peak <= 4 * 65536
        finally:
            for sock in clients:
                sock.close()


def test_receive_times_out_and_a_closed_hub_is_an_error_not_silence() -> None:
    hub = LoopbackHub().start()
    bus = SofthilBus(f"127.0.0.1:{hub.port}")
    try:
        assert bus.recv(0.01) is None
        assert not connection_closed(bus)
        hub.stop()
        with pytest.raises(can.CanOperationError, match="closed the connection"):
            bus.recv(TIMEOUT)
        assert connection_closed(bus)
    finally:
        bus.shutdown()
        hub.stop()


def test_a_malformed_record_from_the_hub_is_an_error_not_skipped() -> None:
    with socket.socket() as fake:  # greets and acknowledges like a hub, then sends a bad record
        fake.bind(("127.0.0.1", 0))
        fake.listen()
        fake.settimeout(TIMEOUT)
        server: list[socket.socket] = []

        def serve() -> None:
            conn, _ = fake.accept()
            server.append(conn)
            conn.sendall(b"< hi >")
            conn.recv(100)  # the hello
            bad = bytes.fromhex("1000230100000001") + bytes(8) + b"xy"  # size 16, dlc 1
            conn.sendall(wire.ack() + bad)

        thread = threading.Thread(target=serve)
        thread.start()
        bus = SofthilBus(f"127.0.0.1:{fake.getsockname()[1]}")
        thread.join()
        try:
            with pytest.raises(can.CanOperationError, match="malformed record"):
                bus.recv(TIMEOUT)
            assert connection_closed(bus)
        finally:
            bus.shutdown()
            server[0].close()


def test_connect_failures_name_the_address() -> None:
    with socket.socket() as listener:  # bound, never listening: connection refused
        listener.bind(("127.0.0.1", 0))
        port = listener.getsockname()[1]
        with pytest.raises(can.CanInitializationError, match=f"127.0.0.1:{port}"):
            SofthilBus(f"127.0.0.1:{port}")
    with socket.socket() as stranger:  # listening, but not a hub
        stranger.bind(("127.0.0.1", 0))
        stranger.listen()
        port = stranger.getsockname()[1]
        with pytest.raises(can.CanInitializationError, match="did not answer"):
            SofthilBus(f"127.0.0.1:{port}", connect_timeout=0.05)


def test_only_classic_data_frames_are_sent(hub: LoopbackHub, buses: list[can.BusABC]) -> None:
    bus = binary(hub, buses)
    for bad in (
        can.Message(arbitration_id=0x1, is_remote_frame=True),
        can.Message(arbitration_id=0x1, is_fd=True, data=bytes(12)),
        can.Message(arbitration_id=0x800, is_extended_id=False, data=b"", check=False),
    ):
        with pytest.raises(can.CanOperationError, match="softhil bus"):
            bus.send(bad)


@pytest.mark.parametrize(
    ("channel", "address"),
    [
        ("127.0.0.1:29537", ("127.0.0.1", 29537)),
        ("4000", ("127.0.0.1", 4000)),
        (None, ("127.0.0.1", 29536)),
    ],
)
def test_channel_strings(channel: str | None, address: tuple[str, int]) -> None:
    assert parse_channel(channel) == address


@pytest.mark.parametrize("channel", ["host:port", "127.0.0.1:0", "127.0.0.1:65536"])
def test_bad_channel_strings_name_the_channel(channel: str) -> None:
    with pytest.raises(ValueError, match=channel):
        parse_channel(channel)


def test_bus_specs_for_both_protocols_of_the_hub(hub: LoopbackHub) -> None:
    for text in ("softhil", "softhil:4000", "softhil:127.0.0.1:4000", "loopback:127.0.0.1:4000"):
        spec = BusSpec.parse(text)
        assert BusSpec.parse(str(spec)) == spec
    assert str(BusSpec.parse("softhil")) == "softhil:127.0.0.1:29536"
    bus = open_bus(BusSpec("softhil", "softhil", "127.0.0.1", hub.port))
    try:
        assert isinstance(bus, SofthilBus)
    finally:
        bus.shutdown()


def test_the_entry_point_names_the_bus_class() -> None:
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    target = pyproject["project"]["entry-points"]["can.interface"]["softhil"]
    module, _, name = target.partition(":")
    assert getattr(import_module(module), name) is SofthilBus


def _entry_point_path(tmp_path: Path) -> str:
    """A PYTHONPATH on which python-can finds the ``softhil`` interface by its entry point,
    whether or not the installed softhil's metadata already declares it."""
    info = tmp_path / "softhil_can_interface-0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: softhil-can-interface\nVersion: 0\n"
    )
    (info / "entry_points.txt").write_text("[can.interface]\nsofthil = rigbus.binary:SofthilBus\n")
    return os.pathsep.join([str(tmp_path), str(ROOT)])


def test_python_can_logger_reaches_the_bus_by_interface_name(
    hub: LoopbackHub, buses: list[can.BusABC], tmp_path: Path
) -> None:
    env = {**os.environ, "PYTHONPATH": _entry_point_path(tmp_path), "PYTHONUNBUFFERED": "1"}
    logger = subprocess.Popen(  # no -f: it prints every frame it receives
        [sys.executable, "-m", "can.logger", "-i", "softhil", "-c", f"127.0.0.1:{hub.port}"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=interruptible,  # it is stopped with SIGINT below
    )
    try:
        assert logger.stdout is not None
        assert logger.stdout.readline().startswith("Connected to SofthilBus: softhil binary on")
        sender = binary(hub, buses)
        joined(hub, 2)
        sender.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\xde\xad"))
        sender.send(can.Message(arbitration_id=0x1ABCDEF, is_extended_id=True, data=b""))
        lines = [logger.stdout.readline() for _ in range(3)][1:]  # after "Can Logger (Started"
    finally:
        logger.send_signal(signal.SIGINT)  # can.logger shuts its bus down on Ctrl-C
        _, err = logger.communicate(timeout=TIMEOUT)
    assert re.search(r"ID: +181 +S .*DL: +2 +de ad", lines[0]), (lines, err)
    assert re.search(r"id: +01abcdef +x .*dl: +0 ", lines[1].lower()), (lines, err)
    assert logger.returncode == 0, err


def test_hub_process_serves_both_protocols_and_exits_with_its_pipe() -> None:
    child = HubProcess()
    try:
        a = SofthilBus(f"127.0.0.1:{child.port}")
        t = can.Bus(interface="socketcand", channel="softhil", host="127.0.0.1", port=child.port)
        message = can.Message(arbitration_id=0x80, is_extended_id=False, data=b"\x07")
        for _ in range(3):  # the socketcand client's handshake grace may hold the first ones
            a.send(message)
        same(t.recv(TIMEOUT), message)
        t.send(message)
        same(a.recv(TIMEOUT), message)
        a.shutdown()
        t.shutdown()
    finally:
        child.stop(timeout=TIMEOUT)
    # stopped by its closed standard input, not killed by the timeout's SIGKILL
    assert child._process.returncode == 0


def test_a_batch_arrives_as_its_frames_in_order_in_both_protocols(
    hub: LoopbackHub, buses: list[can.BusABC]
) -> None:
    """send_batch (one write) delivers what send would, frame by frame, to binary and
    socketcand members; send_all uses it where the bus has it and falls back to send."""
    a, b = binary(hub, buses), binary(hub, buses)
    t = ascii_bus(hub, buses)
    joined(hub, 3)
    sent = frames(random.Random(4), 40)
    a.send_batch(sent[:20])
    send_all(a, sent[20:])
    for receiver in (b, t):
        for message in sent:
            same(receiver.recv(TIMEOUT), message)
    send_all(t, sent[:3])  # socketcand's bus has no send_batch: one by one
    for message in sent[:3]:
        same(a.recv(TIMEOUT), message)


def test_a_batch_with_an_invalid_frame_sends_nothing(
    hub: LoopbackHub, buses: list[can.BusABC]
) -> None:
    a, b = binary(hub, buses), binary(hub, buses)
    joined(hub, 2)
    good = can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01")
    remote = can.Message(arbitration_id=0x124, is_extended_id=False, is_remote_frame=True)
    with pytest.raises(can.CanOperationError, match="only classic data frames"):
        a.send_batch([good, remote])
    a.send(can.Message(arbitration_id=0x125, is_extended_id=False, data=b"\x02"))
    received = b.recv(TIMEOUT)
    assert received is not None and received.arbitration_id == 0x125
