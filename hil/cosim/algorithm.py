"""The stepping algorithm: fixed-step Jacobi co-simulation with integer time.

As libcosim splits a master: participants (`hil.cosim.participant`), this algorithm (stepping
and connection transfer), the execution (`hil.cosim.execution`: when to step, the named
step-ahead policy) and observers. Participant `p` with decimation d steps only at ticks that
are multiples of d, with step d h, so slow subsystems cost less. Time is the integer tick k,
t = k h, never accumulated in floats.

One algorithm, two implementations of its inner loop. The fast path steps the FMU participants
in C (`hil.cosim.kernel`) between the ticks where a Python participant or an observer is due: it
makes the same FMI calls with the same arguments as the Python path (`_step_once`), so results
are bit-identical. The Python path is kept as the test oracle (`kernel=False`, SOFTHIL_KERNEL=0)
and for FMUs whose variable types the kernel does not carry. Observers never switch the kernel
off: it stops at their ticks, or samples its values there when it steps on its worker thread.

`start_advance` begins the same stepping on the kernel's worker thread and returns at once, so
that the caller computes while the FMUs step; the next call that needs the state (`advance_to`,
`publish`, `inputs_of`, `set_input`) waits for it. The Python participants due in the interval
are stepped afterwards, from the values the thread sampled at the start of their ticks, where
that changes nothing the FMUs read: they have no outputs (samplers, such as the camera) or
declare that their step never changes them (`outputs_hold`: device nodes, whose outputs change
at SYNC, published); observers due inside the interval see the sampled values at their ticks.
Any other participant due at the interval's first tick has that tick stepped in turn first;
one due inside it declines the thread. Either way the FMI calls, the participants' steps, what
observers see and every value are those of `advance_to`, an FMU failing on the thread included.

Invariant: within a tick every participant reads the inputs computed from the outputs at the
start of the tick (Jacobi), so the result does not depend on the order of participants.
"""

from __future__ import annotations

import contextlib
import operator
import time
from collections.abc import Callable, Mapping, Sequence
from types import MappingProxyType
from typing import Any

import numpy as np

from hil.cosim import kernel as kernel_module
from hil.cosim.participant import (
    Connection,
    FmuParticipant,
    Observer,
    Participant,
    deferrable,
    observer_decimation,
)
from hil.environment import kernel_enabled
from hil.errors import BuildError, FmuError, HilError

# a sampled interval of `start_advance`: (tick, the participants due there, observers watch it)
_Sample = tuple[int, list[Participant], bool]


class Algorithm:
    """Fixed-step co-simulation of participants joined by connections.

    Parameters
    ----------
    participants
        The simulators; names must be unique.
    connections
        Output-to-input links. Each input is driven by at most one connection or external value.
    step
        Macro step h [s]; simulation time is `tick * step`.
    kernel
        Step the FMU participants in C between events: None (default) when it can be built and
        SOFTHIL_KERNEL is not "0"; False never; True always (a failed kernel build raises).
    """

    def __init__(
        self,
        participants: Sequence[Participant],
        connections: Sequence[Connection],
        step: float,
        *,
        kernel: bool | None = None,
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
        # "participant.variable" of every output, by participant and output (built once: a
        # publish at every SYNC would otherwise format each key anew)
        self._output_keys = {
            p.name: {n: f"{p.name}.{n}" for n in p.output_names()} for p in participants
        }
        # participants whose step changes no output (none, or `outputs_hold`): a step publishes
        # nothing new, so it is not published after one, and it may be stepped after the FMUs'
        # ticks (`start_advance`)
        self._held = {p.name for p in participants if deferrable(p)}
        # every value by "participant.variable"; after the kernel stepped, its FMUs' values are
        # in the kernel's array and copied here only when asked for (`values`, `_refresh`): the
        # plant's loop reads what it needs from the array (`reader`, `inputs_of`)
        self._values: dict[str, float] = {}
        self._stale = False  # the kernel stepped since its values were copied into `_values`
        # the kernel's array as floats (`_current`): read only while stale, made anew after each
        # kernel step, kept up to date by `_publish` in between
        self._snapshot: list[float] | None = None
        self._view = MappingProxyType(self._values)  # what observers get: read-only
        self._kernel: kernel_module.Kernel | None = None
        self._kernel_synced = False
        # a started `start_advance`: its first and last tick and what is due inside it, by tick
        self._ahead: tuple[int, int, list[_Sample]] | None = None
        self._no_thread = False  # the kernel could not start its worker thread
        # [s] of wall time in the kernel's stepping on this thread: what its worker could take
        # over (the plant times its first periods by it)
        self.kernel_seconds = 0.0
        self._initialise()
        if kernel is None:
            kernel = kernel_enabled()
            try:
                self._kernel = self._make_kernel() if kernel else None
            except BuildError:
                self._kernel = None  # no compiler: the Python path is the reference anyway
        elif kernel:
            self._kernel = self._make_kernel()

    @property
    def values(self) -> dict[str, float]:
        """Every value by "participant.variable", current (the caller must not change it)."""
        self._join()
        self._refresh()
        return self._values

    def _refresh(self) -> None:
        """Copy the values the kernel stepped into `_values`, if it stepped since."""
        if self._stale:
            self._values.update(zip(self._fast_keys, self._fresh(self._current()), strict=True))
            self._stale = False

    def _current(self) -> list[float]:
        """The kernel's values by slot, as floats (one conversion until the kernel steps)."""
        snapshot = self._snapshot
        if snapshot is None:
            snapshot = self._snapshot = self._array.tolist()
        return snapshot

    def _kernel_stepped(self) -> None:
        """The kernel's array changed: `_values` and the snapshot are out of date."""
        self._stale = True
        self._snapshot = None

    def reader(self, keys: Sequence[str]) -> Callable[[], tuple[float, ...]]:
        """A function giving the current values of `keys` ("participant.variable"), in order,
        as a tuple: what the plant records at every SYNC, read without `values`' copy of the
        kernel's array (the FMUs' values from its floats, the others as published)."""
        keys = list(keys)
        for key in keys:
            if key not in self._values:
                raise HilError(f"no value {key!r}: not an output of any participant")
        from_dict = _getter(keys)
        values = self._values
        if self._kernel is None:
            return lambda: from_dict(values)
        fast = set(self._fast_keys)
        fast_keys = [k for k in keys if k in fast]
        slow_keys = [k for k in keys if k not in fast]
        from_array = _getter([self._slots[k] for k in fast_keys])
        from_slow = _getter(slow_keys)
        position = {k: i for i, k in enumerate(fast_keys + slow_keys)}
        in_order = _getter([position[k] for k in keys])

        def read() -> tuple[float, ...]:
            self._join()
            if self._stale:
                return in_order(from_array(self._current()) + from_slow(values))
            return from_dict(values)

        return read

    @property
    def uses_kernel(self) -> bool:
        """Whether FMU participants are stepped in C between events."""
        return self._kernel is not None

    def _make_kernel(self) -> kernel_module.Kernel | None:
        """Bind the FMU participants with Real, Integer and Boolean variables to the kernel;
        every other participant (and an FMU with other types) stays in Python."""
        self._slots = {key: i for i, key in enumerate(self._values)}
        fast: list[FmuParticipant] = []
        for p in self.participants.values():
            if isinstance(p, FmuParticipant) and all(
                p.slave.variable_type(n) in kernel_module.TYPES
                for n in (*p.input_names(), *p.output_names())
            ):
                fast.append(p)
        if not fast:
            return None
        links: dict[str, list[tuple[str, int, float, float]]] = {}
        for p in fast:
            links[p.name] = []
            for variable, source, gain, offset in self._connections[p.name]:
                if source not in self._slots:
                    return None  # an output its participant never published
                links[p.name].append((variable, self._slots[source], gain, offset))
        plan = [
            (
                p.name,
                p.slave,
                p.decimation,
                [(n, p.slave.variable_type(n)) for n in p.input_names()],
                [
                    (n, p.slave.variable_type(n), self._slots[f"{p.name}.{n}"])
                    for n in p.output_names()
                ],
            )
            for p in fast
        ]
        kernel = kernel_module.Kernel(plan, links, len(self._slots), self.step)
        # numpy's stubs take no ctypes array, although one exports the buffer protocol
        self._array = np.frombuffer(kernel.values, dtype=np.float64)  # type: ignore[call-overload]
        self._fast = fast
        self._slow = [p for p in self.participants.values() if p not in fast]
        self._fast_keys = [f"{p.name}.{n}" for p in fast for n in p.output_names()]
        self._fast_slots = [self._slots[key] for key in self._fast_keys]
        self._fresh = _getter(self._fast_slots)
        # the Python participants' connections by the slots of their sources: their inputs from
        # a row the kernel sampled (`_sampled_inputs`)
        self._row_links = {
            p.name: [
                (v, self._slots[source], g, o) for v, source, g, o in self._connections[p.name]
            ]
            for p in self._slow
        }
        return kernel

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

    def _initialise(self) -> None:
        """The values at t = 0. An FMU still in initialisation mode recomputes its initial
        outputs from the inputs set there (FMI 2.0 initial unknowns), so the connected values
        are passed along until they stop changing (at most one pass per such FMU: the declared
        dependencies are acyclic); then each leaves initialisation mode. Without this an output
        that depends on an input (a segment's pressures on its piston) would start from the
        input's declared start value instead of the connected one."""
        for p in self.participants.values():
            self._publish(p)
        initializing = [
            p
            for p in self.participants.values()
            if isinstance(p, FmuParticipant) and p.slave.initializing
        ]
        for _ in initializing:
            before = dict(self._values)
            for p in initializing:
                p.set_inputs(self.inputs_of(p.name))
                self._publish(p)
            if self._values == before:
                break
        for p in initializing:
            p.slave.exit_initialization()
            self._publish(p)

    def _publish(self, participant: Participant) -> None:
        outputs = participant.get_outputs()
        keys = self._output_keys[participant.name]
        published = [
            (keys.get(name) or f"{participant.name}.{name}", value)
            for name, value in outputs.items()
        ]
        self._values.update(published)
        if self._kernel_synced:
            array = self._kernel.values  # type: ignore[union-attr]
            snapshot = self._snapshot
            slots = self._slots
            for key, value in published:
                slot = slots.get(key)
                if slot is not None:
                    array[slot] = value
                    if snapshot is not None:
                        snapshot[slot] = array[slot]  # as the array holds it

    def publish(self, participant: str) -> None:
        """Refresh a participant's outputs after an event changed them between ticks (a device
        node latching a command at SYNC), so the next tick transfers the new values."""
        self._join()
        self._publish(self._participant(participant))

    def _participant(self, name: str) -> Participant:
        try:
            return self.participants[name]
        except KeyError:
            raise HilError(f"no participant {name!r}") from None

    def inputs_of(self, participant: str) -> dict[str, float]:
        """The inputs `participant` would receive now: externals and connected outputs."""
        self._join()
        self._participant(participant)
        if self._stale and participant in self._row_links:  # from the kernel's array
            return self._sampled_inputs(participant, self._current())
        return self._inputs(participant, self._values)

    def _inputs(self, participant: str, outputs: Mapping[str, float]) -> dict[str, float]:
        """`participant`'s inputs from its externals and `outputs` (by "participant.output")."""
        values = dict(self._externals[participant])
        for variable, source, gain, offset in self._connections[participant]:
            values[variable] = gain * outputs[source] + offset
        return values

    def _sampled_inputs(self, participant: str, row: Sequence[float]) -> dict[str, float]:
        """`_inputs` from a row of values the kernel sampled (by slot) instead of `values`."""
        values = dict(self._externals[participant])
        for variable, slot, gain, offset in self._row_links[participant]:
            values[variable] = gain * row[slot] + offset
        return values

    @property
    def time(self) -> float:
        return self.tick * self.step

    def set_input(self, participant: str, variable: str, value: float) -> None:
        """An external value (a device node's output) held until changed."""
        self._join()
        key = f"{participant}.{variable}"
        if key in self._driven:
            raise HilError(f"{key} is driven by a connection and cannot be set externally")
        if variable not in self._participant(participant).input_names():
            raise HilError(f"{participant} has no input {variable!r}")
        self._externals[participant][variable] = value
        if self._kernel is not None and self.participants[participant] in self._fast:
            self._kernel.set_external(participant, variable, value)

    def add_observer(self, observer: Observer) -> None:
        self._join()
        self._refresh()
        self.observers.append(observer)
        observer.observe(self.tick, self._view)

    def advance_to(self, tick: int) -> None:
        """Step all participants until simulation tick `tick`."""
        self._join()
        if self._kernel is not None:
            self._advance_in_kernel(tick)
            return
        while self.tick < tick:
            self._step_once()

    def _advance_in_kernel(self, tick: int) -> None:
        """The FMUs in C up to the next tick where a Python participant is due; at that tick
        the Python participants read their inputs from the values at its start (Jacobi), the
        kernel steps the FMUs one tick, then the Python participants step and publish. The
        kernel also stops where an observer is due, which then sees the values there."""
        self._take_over()
        slow = self._slow
        while self.tick < tick:
            k = self.tick
            next_due = min(
                [
                    tick,
                    *(-(-k // p.decimation) * p.decimation for p in slow),
                    *((k // d + 1) * d for d in map(observer_decimation, self.observers)),
                ]
            )
            if next_due > k:
                self._kernel_advance(k, next_due)
                self._observe()
                continue
            due = [p for p in slow if k % p.decimation == 0]
            inputs = [self.inputs_of(p.name) for p in due]
            self._kernel_advance(k, k + 1)
            self.tick = k
            self._step_participants(k, due, inputs)
            self.tick = k + 1
            self._observe()

    def _observe(self) -> None:
        """The observers due at the current tick see every value."""
        t = self.tick
        due = [o for o in self.observers if t % observer_decimation(o) == 0]
        if due:
            self._refresh()
            for observer in due:
                observer.observe(t, self._view)

    def _observe_row(self, tick: int, row: Sequence[float]) -> None:
        """The observers due at `tick` see the values the kernel's worker sampled there (the
        Python participants' outputs held in the interval, as published)."""
        due = [o for o in self.observers if tick % observer_decimation(o) == 0]
        if due:
            values = dict(self._values)
            values.update(zip(self._fast_keys, self._fresh(row), strict=True))
            view = MappingProxyType(values)
            for observer in due:
                observer.observe(tick, view)

    def _take_over(self) -> None:
        """The kernel takes over the Python path's state, if the Python path stepped last."""
        kernel = self._kernel
        assert kernel is not None
        if not self._kernel_synced:
            kernel.load_last_inputs([p._last_inputs for p in self._fast])
            for key, slot in self._slots.items():
                kernel.values[slot] = self._values[key]
            self._kernel_synced = True

    def start_advance(self, tick: int, spin: float = 0.0) -> bool:
        """Begin stepping to `tick` on the kernel's worker thread and return: True if it began
        (or is done), False if the interval needs Python between its ticks (no kernel, a
        participant whose step may change its outputs due after the first tick, no thread to
        be had), when nothing was done. `spin` [s]: how long the waiting caller polls before it
        sleeps."""
        self._join()
        k = self.tick
        if self._kernel is None or tick <= k or self._no_thread:
            return False
        due: dict[int, list[Participant]] = {}
        for p in self._slow:
            d = p.decimation
            for e in range(-(-k // d) * d, tick, d):
                if e > k and p.name not in self._held:
                    return False  # its outputs may feed the FMUs inside the interval
                due.setdefault(e, []).append(p)
        self._take_over()
        begin = k
        first = due.get(k, [])
        if not all(p.name in self._held for p in first):  # tick k in turn, as advance_to does
            inputs = [self.inputs_of(p.name) for p in first]
            self._kernel_advance(k, k + 1)
            self._step_participants(k, first, inputs)
            self.tick = begin = k + 1
            self._observe()
            del due[k]
            if begin >= tick:
                return True
        watched = {
            e
            for d in map(observer_decimation, self.observers)
            for e in range(begin // d * d + d, tick, d)
        }
        # stepped or observed after the worker, from the values sampled at their ticks
        samples = [(e, due.get(e, []), e in watched) for e in sorted(watched.union(due))]
        try:
            self._kernel.start(begin, tick, [e for e, _, _ in samples], spin)
        except HilError:  # no thread to be had: in turn, now and from here on
            self._no_thread = True
            self.advance_to(tick)
            return True
        self._ahead = (begin, tick, samples)
        return True

    def _join(self) -> None:
        """Wait for a job `start_advance` began, if any (every call that touches the state)."""
        if self._ahead is not None:
            self._finish_ahead()

    def _finish_ahead(self) -> None:
        """Wait for `start_advance`'s job, then, tick by tick, show the observers due inside it
        and step the samplers due there, from the values sampled at the tick (Jacobi: its
        start), up to a failing tick; the observers due at the last tick reached see it; raise
        the FmuError `advance_to` would have raised."""
        assert self._ahead is not None and self._kernel is not None
        begin, tick, samples = self._ahead
        self._ahead = None
        kernel = self._kernel
        rows, error = kernel.finish(len(samples))
        self._kernel_stepped()
        done = kernel.ticks_done
        for (e, due, watched), row in zip(samples, rows, strict=True):
            if e >= done:
                break
            if watched:
                self._observe_row(e, row)
            self._step_participants(e, due, [self._sampled_inputs(p.name, row) for p in due])
        self.tick = done
        if done > begin:
            self._observe()
        if error is not None:
            raise error

    def settle(self) -> None:
        """Wait for a job `start_advance` began (its FmuError dropped: the caller is stopping)
        and stop the kernel's worker thread whatever else is raised, so that the process may
        fork; `start_advance` starts a new one."""
        try:
            with contextlib.suppress(FmuError):
                self._join()
        finally:
            if self._kernel is not None:
                self._kernel.stop()

    def _kernel_advance(self, k_begin: int, k_end: int) -> None:
        kernel = self._kernel
        assert kernel is not None
        started = time.perf_counter()
        try:
            kernel.advance(k_begin, k_end)
        finally:
            self.kernel_seconds += time.perf_counter() - started
            self._kernel_stepped()
            self.tick = kernel.ticks_done

    def _step_participants(
        self, k: int, due: list[Participant], inputs: list[dict[str, float]]
    ) -> None:
        """Tick k of the participants due (Jacobi: `inputs` were read at the tick's start),
        then their outputs published."""
        for p, values in zip(due, inputs, strict=True):
            if values:
                p.set_inputs(values)
            p.step(k * self.step, p.decimation * self.step)
        for p in due:
            if p.name not in self._held:
                self._publish(p)

    def _step_once(self) -> None:
        if self._kernel_synced:  # the kernel stepped last: hand its state back to Python
            self._refresh()
            self._kernel.store_last_inputs([p._last_inputs for p in self._fast])  # type: ignore[union-attr]
            self._kernel_synced = False
        k = self.tick
        due = [p for p in self.participants.values() if k % p.decimation == 0]
        inputs = [self.inputs_of(p.name) for p in due]
        self._step_participants(k, due, inputs)
        self.tick = k + 1
        self._observe()


def _getter(keys: Sequence[Any]) -> Callable[[Any], tuple[Any, ...]]:
    """The items at `keys` of a sequence or mapping, in one call: operator.itemgetter, always
    a tuple (itemgetter of one key gives the item, of none is an error)."""
    if len(keys) > 1:
        return operator.itemgetter(*keys)
    keys = tuple(keys)
    return lambda items: tuple(items[k] for k in keys)
