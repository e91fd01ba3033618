"""Busy polling on the run's own hub (`busy_poll` of `SofthilBus` and `HostedBus`): a receive
polls without sleeping for its budget, then sleeps as before; it never outlasts its timeout,
still takes what is already there with a zero timeout, and `hil run` turns it on only where the
two processes have a core each."""

from __future__ import annotations

import os
import select
import threading
import time
import types
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

import hil.bus.hosted as hosted_module
import rigbus.binary as binary_module
from hil import run_bus
from hil.bus.hosted import HostedBus
from hil.bus.loopback import LoopbackHub
from hil.errors import HilError
from hil.run import RunOptions
from hil.run_bus import BUSY_POLL
from rigbus.binary import SofthilBus, busy_poll_seconds
from rigbus.canbus import BusOpenError, BusSpec, open_bus
from tests.test_binary_bus import (  # noqa: F401 - the autouse guard applies here too
    TIMEOUT,
    _guard_blocking_sockets,
    joined,
)
from tests.test_hosted_bus import binary_client, connect

FRAME = can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02")


@pytest.fixture
def hub() -> Iterator[LoopbackHub]:
    with LoopbackHub(handshake_grace=0.0) as h:
        yield h


def later(seconds: float, action: object) -> threading.Thread:
    thread = threading.Timer(seconds, action)  # type: ignore[arg-type]
    thread.start()
    return thread


def count_selects(monkeypatch: pytest.MonkeyPatch) -> list[float | None]:
    """The timeouts of every select the binary bus makes from now on."""
    calls: list[float | None] = []

    def counting(r: list, w: list, x: list, timeout: float | None = None) -> tuple:
        calls.append(timeout)
        return select.select(r, w, x, timeout)

    monkeypatch.setattr(binary_module, "select", types.SimpleNamespace(select=counting))
    return calls


def count_yields(monkeypatch: pytest.MonkeyPatch, module: types.ModuleType) -> list[None]:
    """Every os.sched_yield that `module` makes from now on."""
    calls: list[None] = []

    def counting() -> None:
        calls.append(None)
        os.sched_yield()

    fake_os = types.SimpleNamespace(**{**vars(os), "sched_yield": counting})
    monkeypatch.setattr(module, "os", fake_os)
    return calls


def received_with_zero_timeouts(bus: can.BusABC) -> can.Message:
    """The next frame, asked for with a zero timeout until it comes (bounded)."""
    for _ in range(10_000):
        message = bus.recv(0.0)
        if message is not None:
            return message
        time.sleep(0.001)
    raise AssertionError("no frame came")


@pytest.mark.parametrize("budget", [0.0, 0.9])
def test_a_busy_polling_softhil_bus_reads_a_late_frame_without_sleeping(
    hub: LoopbackHub, monkeypatch: pytest.MonkeyPatch, budget: float
) -> None:
    receiver = SofthilBus(f"127.0.0.1:{hub.port}", busy_poll=budget)
    sender = SofthilBus(f"127.0.0.1:{hub.port}")
    try:
        joined(hub, 2)
        assert receiver.busy_poll == budget
        selects = count_selects(monkeypatch)
        yields = count_yields(monkeypatch, binary_module)
        timer = later(0.1, lambda: sender.send(FRAME))
        message = receiver.recv(TIMEOUT)
        timer.join()
        assert message is not None and bytes(message.data) == b"\x01\x02"
        # within its budget the bus never sleeps in select, and it yields the core as it polls;
        # without one it sleeps at once
        assert (selects == []) == (budget > 0.0), selects
        assert (yields != []) == (budget > 0.0)
    finally:
        receiver.shutdown()
        sender.shutdown()


def test_busy_polling_ends_at_the_receive_timeout_and_a_zero_timeout_still_reads(
    hub: LoopbackHub,
) -> None:
    receiver = SofthilBus(f"127.0.0.1:{hub.port}", busy_poll=1.0)
    sender = SofthilBus(f"127.0.0.1:{hub.port}")
    try:
        joined(hub, 2)
        start = time.monotonic()
        assert receiver.recv(0.05) is None  # the timeout wins over a longer budget
        assert time.monotonic() - start < 0.9
        sender.send(FRAME)
        assert received_with_zero_timeouts(receiver).arbitration_id == 0x123
    finally:
        receiver.shutdown()
        sender.shutdown()


@pytest.mark.parametrize("budget", [0.0, 0.9])
def test_a_busy_polling_hosted_bus_turns_its_hub_without_sleeping(
    budget: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    hosted = HostedBus("sim0", handshake_grace=0.0, busy_poll=budget)
    try:
        (client,) = connect(hosted, binary_client)
        try:
            turns: list[float | None] = []
            poll = hosted.hub.poll

            def recorded(timeout: float | None) -> None:
                turns.append(timeout)
                poll(timeout)

            hosted.hub.poll = recorded  # type: ignore[method-assign]
            yields = count_yields(monkeypatch, hosted_module)
            timer = later(0.1, lambda: client.send(FRAME))
            message = hosted.recv(TIMEOUT)
            timer.join()
            assert message is not None and message.arbitration_id == 0x123
            sleeping = [t for t in turns if t != 0.0]
            assert (sleeping == []) == (budget > 0.0), sleeping[:3]
            assert (yields != []) == (budget > 0.0)
            turns.clear()
            start = time.monotonic()
            assert hosted.recv(0.05) is None  # the timeout still ends the wait, budget or not
            assert time.monotonic() - start < 0.5
            assert turns and all(t == 0.0 for t in turns) == (budget > 0.0)
            client.send(FRAME)  # a zero timeout still turns the hub once, and takes it
            assert received_with_zero_timeouts(hosted).arbitration_id == 0x123
        finally:
            client.shutdown()
    finally:
        hosted.shutdown()


@pytest.mark.parametrize("value", [-0.001, 1.5, "nan", "inf", "fast", None])
def test_a_busy_poll_that_is_not_seconds_in_range_is_refused_by_name(
    hub: LoopbackHub, value: object
) -> None:
    with pytest.raises(ValueError, match="busy_poll"):
        busy_poll_seconds(value)
    with pytest.raises(can.CanInitializationError, match="softhil busy_poll"):
        SofthilBus(f"127.0.0.1:{hub.port}", busy_poll=value)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="busy_poll"):
        HostedBus("sim0", busy_poll=value)  # type: ignore[arg-type]


def test_the_bus_spec_carries_busy_poll_to_the_softhil_bus_and_nothing_else(
    hub: LoopbackHub,
) -> None:
    spec = BusSpec.parse(f"softhil:127.0.0.1:{hub.port},busy_poll=0.25")
    assert str(spec) == f"softhil:127.0.0.1:{hub.port},busy_poll=0.25"
    assert BusSpec.parse(str(spec)) == spec
    bus = open_bus(spec)
    try:
        assert isinstance(bus, SofthilBus) and bus.busy_poll == 0.25
    finally:
        bus.shutdown()
    assert open_bus(BusSpec.parse(f"softhil:{hub.port}")).busy_poll == 0.0  # type: ignore[attr-defined]
    with pytest.raises(BusOpenError, match="busy_poll 'x'"):
        open_bus(BusSpec.parse(f"softhil:{hub.port},busy_poll=x"))
    with pytest.raises(ValueError, match="softhil takes only busy_poll, not 'bitrate'"):
        BusSpec.parse("softhil:29536,bitrate=500000")
    with pytest.raises(ValueError, match="loopback takes no options"):
        BusSpec.parse("loopback:29536,busy_poll=0.1")


def test_hil_run_busy_polls_only_with_a_hosted_hub_two_cores_and_no_pacing(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv("SOFTHIL_BUSY_POLL", raising=False)
    lockstep, paced = RunOptions(out=tmp_path), RunOptions(out=tmp_path, realtime=True)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    assert run_bus.hub_busy_poll("plant", lockstep) == BUSY_POLL > 0.0
    assert run_bus.hub_busy_poll("plant", paced) == 0.0
    assert run_bus.hub_busy_poll("process", lockstep) == 0.0
    assert run_bus.hub_busy_poll("thread", lockstep) == 0.0
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    assert run_bus.hub_busy_poll("plant", lockstep) == 0.0  # one core: polling would starve
    monkeypatch.setenv("SOFTHIL_BUSY_POLL", "0.004")
    assert run_bus.hub_busy_poll("thread", paced) == 0.004  # the user's word wins
    monkeypatch.setenv("SOFTHIL_BUSY_POLL", "2")
    with pytest.raises(HilError, match="SOFTHIL_BUSY_POLL: softhil busy_poll '2'"):
        run_bus.hub_busy_poll("plant", lockstep)
