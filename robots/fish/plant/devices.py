"""The soft fish's device nodes (issue 13): a valve driver per tail channel and the canister's
pressure monitor, under the DeviceNode contract of hil/devices.py.

Invariant: a valve's command is latched at SYNC only (synchronous, as a drive's), and then
ends itself: `open_time` is the time the supply stays open from that SYNC, timed by the driver
on the plant's ticks. The controller repeats the remaining time every cycle, so a controller
that stops talking leaves every valve closed (vented) at most one pulse later: fail-safe. This
is the one output that changes between SYNCs, and it does so only as the latched command says.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from hil.devices import HEARTBEAT, STATUS, SyncContext, clamp
from rigbus.protocol import COUNTER_MODULO, NMT_OPERATIONAL, Frame, GenericFrame, Heartbeat

# ValveStatus.state (the DBC's value table)
CLOSED, OPENING, OPEN, VENTING = 0, 1, 2, 3
FAULT_NO_SUPPLY = 1  # ValveStatus.fault: the supply is below the regulator's set pressure
FAULT_OVER_PRESSURE = 16  # the channel beyond its limit: the driver vents it
VENTED_BELOW = 2e3  # [Pa gauge] a closed channel below this reads "closed", above "venting"
SPOOL_OPEN = 0.99  # spool position beyond which the valve reads "open"


@dataclass
class ValveNode:
    """Valve n's driver: ValveCommand<n> latched at SYNC (open for `open_time` from this SYNC,
    or vent now), ValveStatus<n> answered at every SYNC (state, channel gauge pressure, fault
    bits, the SYNC's counter). A channel beyond `max_pressure` is vented until it falls below
    90 % of it (fault 16); a supply below `p_set` - 1 % sets fault 1 (the canister is empty)."""

    node: int
    tick_length: float  # the plant's tick [s]
    p_set: float  # the regulator's set pressure [Pa abs]
    max_pressure: float  # [Pa gauge]
    pressure_range: tuple[float, float] = (-math.inf, math.inf)  # ValveStatus.p_channel
    heartbeat_node: int = 1
    decimation: int = 1  # steps every tick: it times its own pulse
    pending: GenericFrame | None = None
    close_tick: int = 0  # the supply is open while the tick is below it
    tick: int = 0
    vent_requested: bool = False
    over_pressure: bool = False
    no_supply: bool = False
    state: int = CLOSED
    missed: int = 0
    stale: int = 0
    pulses: int = 0
    name: str = field(init=False)

    def __post_init__(self) -> None:
        self.name = f"valve_driver{self.node}"

    def input_names(self) -> list[str]:
        return ["opening", "p_channel", "p_supply"]

    def output_names(self) -> list[str]:
        return ["open", "state"]

    def set_inputs(self, values: Mapping[str, float]) -> None:
        """Inputs are read at SYNC through `act`."""

    def step(self, time: float, step: float) -> None:
        self.tick = round(time / self.tick_length) + 1  # the tick this step ends at

    def get_outputs(self) -> dict[str, float]:
        return {"open": 1.0 if self._open() else 0.0, "state": float(self.state)}

    def _open(self) -> bool:
        return self.tick < self.close_tick and not self.over_pressure

    @property
    def fault(self) -> int:
        return (FAULT_NO_SUPPLY if self.no_supply else 0) | (
            FAULT_OVER_PRESSURE if self.over_pressure else 0
        )

    def accepts(self, frame: Frame) -> bool:
        return (
            isinstance(frame, GenericFrame)
            and frame.kind == "ValveCommand"
            and frame.index == self.node
        )

    def receive(self, frame: Frame) -> None:
        self.pending = frame

    def act(self, sync: SyncContext, inputs: Mapping[str, float]) -> list[tuple[int, Frame]]:
        """Latch the last period's command, guard the channel, answer with the status."""
        self.tick = sync.tick
        expected = (sync.cycle - 1) % COUNTER_MODULO
        command = self.pending
        self.pending = None
        if command is not None and int(command.signals["counter"]) == expected:
            self.vent_requested = bool(int(command.signals["vent"]))
            open_time = 0.0 if self.vent_requested else float(command.signals["open_time"])
            ticks = round(open_time / self.tick_length)
            if ticks > 0 and not self._open():
                self.pulses += 1
            self.close_tick = sync.tick + ticks
        elif command is not None:
            self.stale += 1
        elif sync.tick > 0:
            self.missed += 1
        p_channel, p_supply = inputs["p_channel"], inputs["p_supply"]
        if not self.over_pressure and p_channel > self.max_pressure:
            self.over_pressure = True
        elif self.over_pressure and p_channel < 0.9 * self.max_pressure:
            self.over_pressure = False
        self.no_supply = p_supply < 0.99 * self.p_set
        if self._open():
            self.state = OPEN if inputs["opening"] >= SPOOL_OPEN else OPENING
        elif inputs["opening"] > 1.0 - SPOOL_OPEN or p_channel > VENTED_BELOW:
            self.state = VENTING
        else:
            self.state = CLOSED
        sent: list[tuple[int, Frame]] = []
        if sync.heartbeat:
            sent.append((HEARTBEAT, Heartbeat(self.heartbeat_node, NMT_OPERATIONAL)))
        status = {
            "state": self.state,
            "p_channel": clamp(p_channel, *self.pressure_range),
            "fault": self.fault,
            "counter": sync.counter,
        }
        sent.append((STATUS, GenericFrame("ValveStatus", self.node, status)))
        return sent


@dataclass
class CanisterNode:
    """The canister's pressure monitor: CanisterStatus at every SYNC (canister and supply
    pressure, gas left, the SYNC's counter), saturated to the DBC's ranges."""

    ranges: Mapping[str, tuple[float, float]]  # per CanisterStatus signal, from the DBC
    heartbeat_node: int = 3
    name: str = "canister"
    decimation: int = 1

    def input_names(self) -> list[str]:
        return ["p_canister", "p_supply", "m_canister"]

    def output_names(self) -> list[str]:
        return []

    def set_inputs(self, values: Mapping[str, float]) -> None:
        """Inputs are read at SYNC through `act`."""

    def step(self, time: float, step: float) -> None:
        """A monitor: nothing between SYNCs."""

    def get_outputs(self) -> dict[str, float]:
        return {}

    def accepts(self, frame: Frame) -> bool:
        return False

    def receive(self, frame: Frame) -> None:  # pragma: no cover - accepts nothing
        raise AssertionError("the canister monitor receives no frames")

    def act(self, sync: SyncContext, inputs: Mapping[str, float]) -> list[tuple[int, Frame]]:
        values = {
            "p_canister": inputs["p_canister"],
            "p_supply": inputs["p_supply"],
            "gas_left": inputs["m_canister"],
        }
        status = {k: clamp(v, *self.ranges[k]) for k, v in values.items()}
        status["counter"] = sync.counter
        sent: list[tuple[int, Frame]] = []
        if sync.heartbeat:
            sent.append((HEARTBEAT, Heartbeat(self.heartbeat_node, NMT_OPERATIONAL)))
        sent.append((STATUS, GenericFrame("CanisterStatus", None, status)))
        return sent
