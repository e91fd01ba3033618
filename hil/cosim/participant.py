"""The participants of a co-simulation: what the algorithm steps and what watches it.

A `Participant` is one simulator: an FMU through fmpy (`FmuParticipant`), a device node, the
camera, or anything with the same five methods. An `Observer` watches values at its ticks and
changes nothing. A `Connection` copies an output to an input at every tick (Jacobi transfer).
Invariant: a participant's outputs change only when it steps or when an event publishes them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
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
    """Sees every value ("participant.variable") at the ticks that are multiples of its
    `decimation` (an optional attribute, default 1: every tick) and at the tick it is added;
    must not change anything. Observers never take the stepping off the C kernel: the kernel
    stops, or samples its values, at their ticks (`hil.cosim.algorithm`)."""

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


def deferrable(participant: Participant) -> bool:
    """Whether stepping `participant` later than the FMUs' ticks changes nothing they read: it
    has no outputs (a sampler, such as the camera), or its step never changes them (they
    change only by events, published: `outputs_hold`, as a device node's between SYNCs)."""
    return not participant.output_names() or getattr(participant, "outputs_hold", False)


def observer_decimation(observer: Observer) -> int:
    """Every how many ticks `observer` observes (its `decimation`, by default every tick)."""
    d = getattr(observer, "decimation", 1)
    if not isinstance(d, int) or d < 1:
        raise HilError(f"observer decimation must be a positive integer, got {d!r}")
    return d
