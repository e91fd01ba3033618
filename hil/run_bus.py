"""The bus a run joins: the plant's and the controller's bus specs, and the run's own hub.

`hil run --bus` names a bus, or the scenario's [bus] does; a loopback bus without a port gets a
hub of the run's own (`serve_hub`: by default the plant's bus is the hub, `hil.bus.hosted`), and
plant and controller then speak its binary records. Invariant: a bus the run is to join is
opened once and closed again before the results folder is made (`check_bus_opens`), so a bus
that cannot be opened is one line, not a failed run.
"""

from __future__ import annotations

import os
import uuid
from contextlib import ExitStack
from dataclasses import replace
from typing import TYPE_CHECKING

from hil.bus.hosted import HostedBus
from hil.bus.loopback import HubProcess, LoopbackHub
from hil.environment import two_cores
from hil.errors import BusError, HilError, ProtocolError
from hil.scenario import Scenario
from rigbus.binary import busy_poll_seconds
from rigbus.canbus import HUB_KINDS, BusOpenError, BusSpec, open_bus

if TYPE_CHECKING:
    import can

    from hil.run import RunOptions

HUB_MODES = ("plant", "process", "thread")
# [s] how long the plant and the controller poll the run's own hub before they sleep, when the
# plant hosts it: each waits for the other once a SYNC, mostly for less than this, and waking
# a sleeping process costs hundreds of microseconds on a virtual machine (6 segments across
# processes, 2 cores: 3.8-5.0x real time -> 6.1-9.3x; 0.3 ms helped one run in three). Each
# poll yields the core to any process that needs it: two such runs at once on 2 cores ran at
# 1.6x each polling without yielding, 3.9-5.9x yielding, 4.7-5.1x sleeping at once
BUSY_POLL = 0.002


def open_spec(spec: BusSpec) -> can.BusABC:
    """The bus `spec` names, opened; BusError if it cannot be."""
    try:
        return open_bus(spec)
    except BusOpenError as exc:
        raise BusError(str(exc)) from exc


def bus_option(options: RunOptions) -> BusSpec | None:
    """--bus as a spec (None: not given, or --inprocess's virtual bus); HilError for a spec
    that cannot be, checked before the results folder is made (a misspelt interface is not a
    failed run)."""
    if not options.bus:
        return None
    if options.inprocess:
        if not options.bus.startswith("virtual"):
            raise HilError(f"--inprocess runs on the virtual bus, not {options.bus}")
        return None
    try:
        spec = BusSpec.parse(options.bus)
    except ValueError as exc:
        raise HilError(str(exc)) from exc
    if spec.kind == "virtual":
        raise HilError("a virtual bus only joins one process: use --inprocess, or --bus loopback")
    return spec


def check_bus_opens(scenario: Scenario, options: RunOptions) -> None:
    """Open the bus the run is to join (not a hub of its own) and close it again, before the
    results folder is made: a bus that cannot be opened is one line, not a failed run whose
    folder then refuses the retry its message suggests."""
    spec = bus_option(options)
    if options.inprocess:
        return
    if spec is None:
        b = scenario.bus
        if b.kind == "virtual" or (b.kind in HUB_KINDS and b.port == 0):
            return  # refused by bus_specs; or the run's own hub
        spec = BusSpec(b.kind, b.channel, b.host, b.port)
    open_spec(spec).shutdown()


def bus_specs(
    scenario: Scenario, options: RunOptions, stack: ExitStack
) -> tuple[BusSpec, BusSpec, HostedBus | None, str | None]:
    """(plant's spec, controller's spec, the plant's bus if the plant hosts the hub, where
    the run's own hub runs if it has one). A loopback bus without a port gets its own hub."""
    given = bus_option(options)
    if options.inprocess:
        channel = f"softhil-{uuid.uuid4().hex[:8]}"  # a private channel per run
        if options.bus and options.bus.startswith("virtual:"):
            channel = options.bus.partition(":")[2]  # a channel named by the user
        spec = BusSpec("virtual", channel)
        return spec, spec, None, None
    if given is not None:
        spec = given
    else:
        b = scenario.bus
        spec = BusSpec(b.kind, b.channel, b.host, b.port or 0)
        if spec.kind == "virtual":
            raise HilError(
                "a virtual bus only joins one process: use --inprocess, or --bus loopback"
            )
    if spec.kind in HUB_KINDS and (options.bus is None and scenario.bus.port == 0):
        # our own hub: plant and controller speak its binary records (the ASCII socketcand
        # protocol stays open on the same port for tools); the hub runs where SOFTHIL_HUB says
        mode = os.environ.get("SOFTHIL_HUB", "plant")
        busy_poll = hub_busy_poll(mode, options)
        assert spec.channel is not None  # the scenario's bus.channel (checked, never empty)
        port, hosted = serve_hub(spec.host, spec.channel, mode, busy_poll, stack)
        extra = (("busy_poll", f"{busy_poll:g}"),) if busy_poll else ()
        spec = replace(spec, kind="softhil", port=port, options=extra)
        return spec, spec, hosted, mode
    return spec, spec, None, None


def hub_busy_poll(mode: str, options: RunOptions) -> float:
    """The busy-poll budget [s] of the run's own hub clients: SOFTHIL_BUSY_POLL if set, else
    BUSY_POLL when the plant hosts the hub, the run is not paced by the wall clock, and this
    process may use two cores or more (the two processes then poll on cores of their own);
    else 0 (a thread or child-process hub shares the cores with both)."""
    text = os.environ.get("SOFTHIL_BUSY_POLL")
    if text is not None:
        try:
            return busy_poll_seconds(text)
        except ValueError as exc:
            raise HilError(f"SOFTHIL_BUSY_POLL: {exc}") from None
    if mode != "plant" or options.realtime:
        return 0.0
    return BUSY_POLL if two_cores() else 0.0


def serve_hub(
    host: str, channel: str, mode: str, busy_poll: float, stack: ExitStack
) -> tuple[int, HostedBus | None]:
    """Start a hub for this run: its port, and the plant's bus if the plant hosts it.
    ``plant`` (the default): the plant's own bus is the hub (`hil.bus.hosted`), one hop and
    one process fewer each way; ``process``: a child process; ``thread``: a thread of this
    process (both measured against it in bench/bench_run.py)."""
    if mode == "plant":
        bus = HostedBus(channel, host, busy_poll=busy_poll)
        stack.callback(bus.shutdown)
        return bus.port, bus
    if mode == "process":
        child = HubProcess(host)
        stack.callback(child.stop)
        return child.port, None
    if mode == "thread":
        hub = LoopbackHub(host).start()
        stack.callback(hub.stop)
        return hub.port, None
    raise HilError(f"SOFTHIL_HUB={mode!r}: must be one of {', '.join(HUB_MODES)}")


def on_another_channel(exc: ProtocolError, bus: object, cycle: int) -> ProtocolError:
    """A controller that never sent SYNC(0) to the hub the plant hosts may have joined another
    channel of it: `exc` saying which, if one did."""
    if not isinstance(bus, HostedBus) or cycle >= 0:
        return exc
    others = bus.elsewhere()
    if not others:
        return exc
    names = ", ".join(repr(name) for name in others)
    return ProtocolError(
        f"{exc}; a client joined the hub's channel {names}, not this run's "
        f"{bus.channel_name!r} (the channel of its bus spec)"
    )
