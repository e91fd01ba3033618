"""The hub hosted in the plant's thread (`hil.bus.hosted.HostedBus`): a member of its own
channel that the other members, binary and socketcand clients, reach as any hub; frames in order
both ways, no echo, timeouts, invalid frames refused whole, and a clear end when it shuts down."""

from __future__ import annotations

import random
import socket
import threading
from collections.abc import Callable, Iterator

import can
import pytest

from hil.bus.hosted import HostedBus
from rigbus.binary import SofthilBus
from tests.test_binary_bus import (  # noqa: F401 - the autouse guard applies here too
    TIMEOUT,
    _guard_blocking_sockets,
    frames,
)


@pytest.fixture
def hosted() -> Iterator[HostedBus]:
    bus = HostedBus("sim0", handshake_grace=0.0)
    yield bus
    bus.shutdown()


def connect(hosted: HostedBus, *makers: Callable[[int], can.BusABC]) -> list[can.BusABC]:
    """Clients made in a thread (their handshakes need the hub) while this thread turns it."""
    made: list[can.BusABC] = []
    errors: list[BaseException] = []

    def make_all() -> None:
        try:
            made.extend(make(hosted.port) for make in makers)
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    thread = threading.Thread(target=make_all)
    thread.start()
    for _ in range(10_000):
        if not thread.is_alive():
            break
        hosted.hub.poll(0.001)
    thread.join(TIMEOUT)
    assert not errors, errors
    assert hosted.hub.clients == len(makers)
    return made


def binary_client(port: int) -> can.BusABC:
    return SofthilBus(f"127.0.0.1:{port}", bus_name="sim0")


def ascii_client(port: int) -> can.BusABC:
    return can.Bus(interface="socketcand", channel="sim0", host="127.0.0.1", port=port)


def key(message: can.Message | None) -> tuple[int, bool, bytes]:
    assert message is not None, "a frame was not received"
    return message.arbitration_id, message.is_extended_id, bytes(message.data)


def test_the_hosted_member_and_both_protocols_exchange_frames_in_order(
    hosted: HostedBus,
) -> None:
    clients = connect(hosted, binary_client, ascii_client)
    try:
        binary, ascii_ = clients
        sent = frames(random.Random(3), 40)
        hosted.send_batch(sent[:20])
        for message in sent[20:]:
            hosted.send(message)
        for client in clients:
            assert [key(client.recv(TIMEOUT)) for _ in sent] == [key(m) for m in sent]
        back = frames(random.Random(4), 30)
        for message in back:
            binary.send(message)
        got = [key(hosted.recv(TIMEOUT)) for _ in back]
        assert got == [key(m) for m in back]
        assert [key(ascii_.recv(TIMEOUT)) for _ in back] == got  # the other client too
        assert hosted.recv(0.02) is None  # no echo of its own frames, nothing left over
        assert binary.recv(0.02) is None
        assert hosted.hub.frames_forwarded == len(sent) + len(back)
    finally:
        for client in clients:
            client.shutdown()


def test_an_invalid_frame_sends_nothing_of_its_batch(hosted: HostedBus) -> None:
    (client,) = connect(hosted, binary_client)
    try:
        good = can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01")
        remote = can.Message(arbitration_id=0x124, is_extended_id=False, is_remote_frame=True)
        with pytest.raises(can.CanOperationError, match="only classic data frames"):
            hosted.send_batch([good, remote])
        too_long = can.Message(arbitration_id=0x800, is_extended_id=False, data=b"")
        with pytest.raises(can.CanOperationError, match="id out of range"):
            hosted.send(too_long)
        assert client.recv(0.05) is None
        hosted.send(good)
        assert key(client.recv(TIMEOUT)) == key(good)
    finally:
        client.shutdown()


def test_receive_times_out_and_shutdown_ends_the_bus_for_everyone(hosted: HostedBus) -> None:
    (client,) = connect(hosted, binary_client)
    try:
        assert hosted.recv(0.01) is None
        port = hosted.port
        hosted.shutdown()
        hosted.shutdown()  # idempotent
        with pytest.raises(can.CanOperationError, match="shut down"):
            hosted.send(can.Message(arbitration_id=1, is_extended_id=False, data=b""))
        with pytest.raises(can.CanOperationError, match="shut down"):
            hosted.recv(0.01)
        with pytest.raises(can.CanOperationError, match="closed the connection"):
            client.recv(TIMEOUT)
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
    finally:
        client.shutdown()


def test_the_sender_of_a_watched_id_is_known_until_its_connection_closes(
    hosted: HostedBus,
) -> None:
    """`watch(id)` remembers which connection last sent that id; `sender_gone` names where it
    was connected from once it has closed (how a run notices a controller started by hand
    leaving), and a newcomer sending the id takes its place."""
    first, other = connect(hosted, binary_client, ascii_client)
    newcomer = None
    try:
        hosted.watch(0x080)
        assert hosted.sender_gone() is None  # nothing sent yet
        first.send(can.Message(arbitration_id=0x080, is_extended_id=False, data=b"\x00"))
        assert key(hosted.recv(TIMEOUT))[0] == 0x080
        other.send(can.Message(arbitration_id=0x081, is_extended_id=False, data=b"\x01"))
        assert key(hosted.recv(TIMEOUT))[0] == 0x081  # another id: still the first's
        other.shutdown()  # not the sender of 0x080
        for _ in range(50):
            hosted.recv(0.01)
        assert hosted.hub.clients == 1 and hosted.sender_gone() is None
        host, port = first._sock.getsockname()  # where the hub saw it connect from
        first.shutdown()
        for _ in range(50):
            hosted.recv(0.01)
            if hosted.sender_gone():
                break
        assert hosted.sender_gone() == f"{host}:{port}"
        (newcomer,) = connect(hosted, binary_client)
        newcomer.send(can.Message(arbitration_id=0x080, is_extended_id=False, data=b"\x01"))
        assert key(hosted.recv(TIMEOUT))[0] == 0x080
        assert hosted.sender_gone() is None
    finally:
        for client in (first, other, newcomer):
            if client is not None:
                client.shutdown()
