"""The co-simulation master: participants, connections, integer time and observers.

Split as in libcosim: a `Participant` is one simulator (an FMU through fmpy, or anything with the
same five methods); `Master` is the algorithm (fixed-step Jacobi stepping with connection
transfer) and the execution (integer tick k, t = k h: time is never accumulated in floats);
observers see read-only values after every tick. Participant `p` with decimation d steps only at
ticks that are multiples of d, with step d h, so slow subsystems cost less.

Invariant: within a tick every participant reads the inputs computed from the outputs at the
start of the tick (Jacobi), so the result does not depend on the order of participants.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Protocol

from hil.errors import HilError
from hil.fmu.slave import FmuSlave


class Participant(Protocol):
    """One simulator in the co-simulation."""

    name: str
    decimation: int

    def input_names(self) -> list[str]: ...
    def output_names(self) -> list[str]: ...
    def set_inputs(self, values: Mapping[str, float]) -> None: ...
    def step(self, time: float, step: float) -> None: ...
    def get_outputs(self) -> dict[str, float]: ...


class Observer(Protocol):
    """Sees every value after each tick; must not change anything."""

    def observe(self, tick: int, values: Mapping[str, float]) -> None: ...


@dataclass(frozen=True)
class Connection:
    """`target` input := gain * `source` output + offset (names are "participant.variable")."""

    source: str
    target: str
    gain: float = 1.0
    offset: float = 0.0


class FmuParticipant:
    """An FMU instance as a participant; Real inputs and outputs go by value reference."""

    def __init__(self, slave: FmuSlave, decimation: int = 1) -> None:
        self.slave = slave
        self.name = slave.instance_name
        self.decimation = decimation
        self._inputs = slave.names("input")
        self._outputs = slave.names("output")
        self._real_outputs = [n for n in self._outputs if slave.variable_type(n) == "Real"]
        self._real_output_vrs = [slave.value_reference(n) for n in self._real_outputs]
        self._other_outputs = [n for n in self._outputs if slave.variable_type(n) != "Real"]
        # value reference of each Real input, None for the other types (set by name)
        self._input_vr = {
            n: slave.value_reference(n) if slave.variable_type(n) == "Real" else None
            for n in self._inputs
        }
        self._last_inputs: dict[str, float] = {}

    def input_names(self) -> list[str]:
        return list(self._inputs)

    def output_names(self) -> list[str]:
        return list(self._outputs)

    def set_inputs(self, values: Mapping[str, float]) -> None:
        last = self._last_inputs
        vrs: list[int] = []
        reals: list[float] = []
        for name, value in values.items():
            if last.get(name) == value:
                continue
            last[name] = value
            vr = self._input_vr[name]
            if vr is None:
                self.slave.set(name, value)
            else:
                vrs.append(vr)
                reals.append(value)
        if vrs:
            self.slave.set_reals(vrs, reals)

    def step(self, time: float, step: float) -> None:
        self.slave.do_step(time, step)

    def get_outputs(self) -> dict[str, float]:
        values = dict(
            zip(self._real_outputs, self.slave.get_reals(self._real_output_vrs), strict=True)
        )
        for name in self._other_outputs:
            values[name] = float(self.slave.get(name))
        return values

    def close(self) -> None:
        self.slave.close()


class Master:
    """Fixed-step co-simulation of participants joined by connections.

    Parameters
    ----------
    participants
        The simulators; names must be unique.
    connections
        Output-to-input links. Each input is driven by at most one connection or external value.
    step
        Macro step h [s]; simulation time is `tick * step`.
    """

    def __init__(
        self,
        participants: Sequence[Participant],
        connections: Sequence[Connection],
        step: float,
    ) -> None:
        if not step > 0.0:
            raise HilError(f"macro step must be positive, got {step}")
        self.step = step
        self.tick = 0
        self.participants = {p.name: p for p in participants}
        if len(self.participants) != len(participants):
            raise HilError("participant names must be unique")
        for p in participants:
            if not isinstance(p.decimation, int) or p.decimation < 1:
                raise HilError(
                    f"{p.name}: decimation must be a positive integer, got {p.decimation}"
                )
        self.observers: list[Observer] = []
        self._externals: dict[str, dict[str, float]] = {p.name: {} for p in participants}
        self._connections: dict[str, list[tuple[str, str, float, float]]] = {
            p.name: [] for p in participants
        }
        driven: set[str] = set()
        for c in connections:
            self._endpoint(c.source, "output")
            target, variable = self._endpoint(c.target, "input")
            if c.target in driven:
                raise HilError(f"connection to {c.target}: the input is already driven")
            driven.add(c.target)
            self._connections[target].append((variable, c.source, c.gain, c.offset))
        self._driven = driven
        self.values: dict[str, float] = {}
        self._view = MappingProxyType(self.values)  # what observers get: read-only
        for p in participants:
            self._publish(p)

    def _endpoint(self, name: str, kind: str) -> tuple[str, str]:
        participant, _, variable = name.partition(".")
        if participant not in self.participants:
            raise HilError(f"connection endpoint {name!r}: no participant {participant!r}")
        names = (
            self.participants[participant].output_names()
            if kind == "output"
            else self.participants[participant].input_names()
        )
        if variable not in names:
            raise HilError(
                f"connection endpoint {name!r}: {participant} has no {kind} {variable!r}"
            )
        return participant, variable

    def _publish(self, participant: Participant) -> None:
        for name, value in participant.get_outputs().items():
            self.values[f"{participant.name}.{name}"] = value

    def publish(self, participant: str) -> None:
        """Refresh a participant's outputs after an event changed them between ticks (a device
        node latching a command at SYNC), so the next tick transfers the new values."""
        self._publish(self._participant(participant))

    def _participant(self, name: str) -> Participant:
        try:
            return self.participants[name]
        except KeyError:
            raise HilError(f"no participant {name!r}") from None

    def inputs_of(self, participant: str) -> dict[str, float]:
        """The inputs `participant` would receive now: externals and connected outputs."""
        self._participant(participant)
        values = dict(self._externals[participant])
        for variable, source, gain, offset in self._connections[participant]:
            values[variable] = gain * self.values[source] + offset
        return values

    @property
    def time(self) -> float:
        return self.tick * self.step

    def set_input(self, participant: str, variable: str, value: float) -> None:
        """An external value (a device node's output) held until changed."""
        key = f"{participant}.{variable}"
        if key in self._driven:
            raise HilError(f"{key} is driven by a connection and cannot be set externally")
        if variable not in self._participant(participant).input_names():
            raise HilError(f"{participant} has no input {variable!r}")
        self._externals[participant][variable] = value

    def add_observer(self, observer: Observer) -> None:
        self.observers.append(observer)
        observer.observe(self.tick, self._view)

    def advance_to(self, tick: int) -> None:
        """Step all participants until simulation tick `tick`."""
        while self.tick < tick:
            self._step_once()

    def _step_once(self) -> None:
        k = self.tick
        due = [p for p in self.participants.values() if k % p.decimation == 0]
        inputs = [self.inputs_of(p.name) for p in due]
        for p, values in zip(due, inputs, strict=True):
            if values:
                p.set_inputs(values)
            p.step(k * self.step, p.decimation * self.step)
        for p in due:
            self._publish(p)
        self.tick = k + 1
        for observer in self.observers:
            observer.observe(self.tick, self._view)
