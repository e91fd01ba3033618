"""Tests for hil.cosim.algorithm: Jacobi transfer, connections, decimation, integer time, observers,
errors.

The master is driven by small mock participants (as in libcosim's tests), never by FMUs, so every
expected value below follows from the stepping rules alone.
"""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Mapping

import pytest

from hil.cosim import Algorithm, Connection, Participant
from hil.errors import HilError

H = 1e-3  # macro step [s]


class Counter:
    """A source: after its k-th step its output `y` is k (it starts at 0)."""

    def __init__(self, name: str, decimation: int = 1) -> None:
        self.name = name
        self.decimation = decimation
        self.steps: list[tuple[float, float]] = []

    def input_names(self) -> list[str]:
        return []

    def output_names(self) -> list[str]:
        return ["y"]

    def set_inputs(self, values: Mapping[str, float]) -> None:
        raise AssertionError(f"{self.name} has no inputs, got {dict(values)}")

    def step(self, time: float, step: float) -> None:
        self.steps.append((time, step))

    def get_outputs(self) -> dict[str, float]:
        return {"y": float(len(self.steps))}


class Relay:
    """Output `y` := input `u` as received before the last step; `y` starts at `initial`.

    Records every input mapping it receives and every (time, step) it is stepped with."""

    def __init__(self, name: str, decimation: int = 1, initial: float = -1.0) -> None:
        self.name = name
        self.decimation = decimation
        self.u = initial
        self.y = initial
        self.received: list[dict[str, float]] = []
        self.steps: list[tuple[float, float]] = []

    def input_names(self) -> list[str]:
        return ["u", "w"]

    def output_names(self) -> list[str]:
        return ["y"]

    def set_inputs(self, values: Mapping[str, float]) -> None:
        self.received.append(dict(values))
        self.u = values.get("u", self.u)

    def step(self, time: float, step: float) -> None:
        self.steps.append((time, step))
        self.y = self.u

    def get_outputs(self) -> dict[str, float]:
        return {"y": self.y}


class Recorder:
    """An observer keeping (tick, copy of the values) of every call."""

    def __init__(self) -> None:
        self.calls: list[tuple[int, dict[str, float]]] = []

    def observe(self, tick: int, values: Mapping[str, float]) -> None:
        self.calls.append((tick, dict(values)))


def chain(order: tuple[str, ...]) -> tuple[Algorithm, Recorder]:
    """src -> a -> b, with the participants and connections listed in the given order."""
    parts: dict[str, Participant] = {
        "src": Counter("src"),
        "a": Relay("a", initial=-100.0),
        "b": Relay("b", initial=-100.0),
    }
    links = [Connection("src.y", "a.u"), Connection("a.y", "b.u")]
    if order[0] != "src":
        links.reverse()
    master = Algorithm([parts[name] for name in order], links, H)
    recorder = Recorder()
    master.add_observer(recorder)
    return master, recorder


def test_chain_has_one_tick_of_delay_per_hop() -> None:
    master, recorder = chain(("src", "a", "b"))
    master.advance_to(6)
    for tick, values in recorder.calls[1:]:
        assert values["src.y"] == tick
        assert values["a.y"] == tick - 1
        assert values["b.y"] == (tick - 2 if tick >= 2 else -100.0)
    assert [tick for tick, _ in recorder.calls] == [0, 1, 2, 3, 4, 5, 6]
    assert recorder.calls[-1][1] == {"src.y": 6.0, "a.y": 5.0, "b.y": 4.0}


def test_jacobi_result_independent_of_participant_order() -> None:
    histories = []
    for order in itertools.permutations(("src", "a", "b")):
        master, recorder = chain(order)
        master.advance_to(8)
        histories.append(recorder.calls)
    assert all(history == histories[0] for history in histories[1:])
    # Gauss-Seidel in the order src, a, b would give b.y = 8 here; Jacobi gives 6.
    assert histories[0][-1][1]["b.y"] == 6.0


def test_gain_and_offset_are_applied_to_the_source_output() -> None:
    src, relay = Counter("src"), Relay("r")
    master = Algorithm([src, relay], [Connection("src.y", "r.u", gain=-2.5, offset=0.75)], H)
    master.advance_to(4)
    # tick k reads src.y = k (the value at the start of the tick)
    assert [values["u"] for values in relay.received] == [-2.5 * k + 0.75 for k in range(4)]
    assert master.values["r.y"] == -2.5 * 3 + 0.75


def test_default_connection_is_identity() -> None:
    connection = Connection("a.y", "b.u")
    assert (connection.gain, connection.offset) == (1.0, 0.0)


def test_decimated_participant_steps_only_at_multiples_of_its_decimation() -> None:
    src, slow = Counter("src"), Relay("slow", decimation=5)
    master = Algorithm([src, slow], [Connection("src.y", "slow.u")], H)
    master.advance_to(23)
    assert [time for time, _ in slow.steps] == [k * H for k in (0, 5, 10, 15, 20)]
    assert {step for _, step in slow.steps} == {5 * H}
    # it reads its input at its own ticks only, from the value at the start of that tick
    assert [values["u"] for values in slow.received] == [0.0, 5.0, 10.0, 15.0, 20.0]
    assert len(src.steps) == 23
    # between its steps its published output holds
    assert master.values["slow.y"] == 20.0


def test_time_is_integer_tick_times_step_never_a_float_sum() -> None:
    n = 100_000
    src, slow = Counter("src"), Relay("slow", decimation=5)
    master = Algorithm([src, slow], [Connection("src.y", "slow.u")], H)
    master.advance_to(n)
    assert master.tick == n
    assert master.time == n * H
    assert master.time == 100.0
    # the accumulated float sum differs, so the assertions above distinguish the two
    assert sum([H] * n) != n * H
    assert [time for time, _ in src.steps] == [k * H for k in range(n)]
    assert [time for time, _ in slow.steps] == [k * H for k in range(0, n, 5)]
    assert slow.steps[-1] == (99_995 * H, 5 * H)


def test_advance_to_a_past_tick_does_nothing() -> None:
    src = Counter("src")
    master = Algorithm([src], [], H)
    master.advance_to(5)
    master.advance_to(3)
    assert master.tick == 5
    assert len(src.steps) == 5


def test_observer_called_at_registration_and_once_per_tick() -> None:
    src = Counter("src")
    master = Algorithm([src], [], H)
    master.advance_to(3)
    recorder = Recorder()
    master.add_observer(recorder)
    assert recorder.calls == [(3, {"src.y": 3.0})]
    master.advance_to(7)
    assert recorder.calls == [(k, {"src.y": float(k)}) for k in range(3, 8)]


def test_initial_values_are_published_before_the_first_tick() -> None:
    master = Algorithm([Counter("src"), Relay("r", initial=4.5)], [], H)
    assert master.values == {"src.y": 0.0, "r.y": 4.5}
    assert master.tick == 0
    assert master.time == 0.0


def test_external_input_persists_until_changed() -> None:
    relay = Relay("r")
    master = Algorithm([relay], [], H)
    master.set_input("r", "u", 3.0)
    master.advance_to(4)
    master.set_input("r", "u", -7.0)
    master.advance_to(6)
    assert [values["u"] for values in relay.received] == [3.0] * 4 + [-7.0] * 2
    assert master.values["r.y"] == -7.0


def test_external_input_and_connection_reach_the_same_participant() -> None:
    src, relay = Counter("src"), Relay("r")
    master = Algorithm([src, relay], [Connection("src.y", "r.u")], H)
    master.set_input("r", "w", 9.0)
    master.advance_to(3)
    assert relay.received == [{"w": 9.0, "u": float(k)} for k in range(3)]


def test_participant_without_inputs_is_not_sent_an_empty_mapping() -> None:
    master = Algorithm([Counter("src")], [], H)
    master.advance_to(3)  # Counter.set_inputs raises if called
    assert master.values["src.y"] == 3.0


@pytest.mark.parametrize(
    ("connection", "message"),
    [
        (Connection("ghost.y", "r.u"), "connection endpoint 'ghost.y': no participant 'ghost'"),
        (Connection("src.y", "ghost.u"), "connection endpoint 'ghost.u': no participant 'ghost'"),
        (Connection("src.z", "r.u"), "connection endpoint 'src.z': src has no output 'z'"),
        (Connection("src.y", "r.z"), "connection endpoint 'r.z': r has no input 'z'"),
        (Connection("r.u", "r.w"), "connection endpoint 'r.u': r has no output 'u'"),
        (Connection("src.y", "r.y"), "connection endpoint 'r.y': r has no input 'y'"),
    ],
)
def test_connection_to_unknown_participant_or_variable(
    connection: Connection, message: str
) -> None:
    with pytest.raises(HilError) as info:
        Algorithm([Counter("src"), Relay("r")], [connection], H)
    assert str(info.value) == message


def test_input_driven_by_two_connections() -> None:
    links = [Connection("src.y", "r.u"), Connection("other.y", "r.u")]
    with pytest.raises(HilError, match=r"connection to r\.u: the input is already driven"):
        Algorithm([Counter("src"), Counter("other"), Relay("r")], links, H)


def test_set_input_on_a_driven_input() -> None:
    master = Algorithm([Counter("src"), Relay("r")], [Connection("src.y", "r.u")], H)
    with pytest.raises(HilError, match=r"^r\.u is driven by a connection"):
        master.set_input("r", "u", 1.0)
    master.set_input("r", "w", 1.0)  # the undriven input of the same participant is fine


def test_set_input_on_an_unknown_variable() -> None:
    master = Algorithm([Relay("r")], [], H)
    with pytest.raises(HilError, match=r"^r has no input 'y'$"):
        master.set_input("r", "y", 1.0)


def test_set_input_on_an_unknown_participant() -> None:
    master = Algorithm([Relay("r")], [], H)
    with pytest.raises(HilError, match="ghost"):
        master.set_input("ghost", "u", 1.0)


def test_duplicate_participant_names() -> None:
    with pytest.raises(HilError, match="participant names must be unique"):
        Algorithm([Relay("r"), Counter("r")], [], H)


def test_observer_cannot_change_the_values_participants_read() -> None:
    class Vandal:
        def observe(self, tick: int, values: Mapping[str, float]) -> None:
            with contextlib.suppress(TypeError):  # a read-only mapping refuses
                values["src.y"] = 99.0  # type: ignore[index]

    src, relay = Counter("src"), Relay("r")
    master = Algorithm([src, relay], [Connection("src.y", "r.u")], H)
    master.add_observer(Vandal())
    master.advance_to(3)
    assert [values["u"] for values in relay.received] == [0.0, 1.0, 2.0]


class Constant:
    """A participant whose one output is a constant."""

    def __init__(self, name: str, value: float) -> None:
        self.name, self.decimation, self.value = name, 1, value

    def input_names(self) -> list[str]:
        return []

    def output_names(self) -> list[str]:
        return ["y"]

    def set_inputs(self, values: Mapping[str, float]) -> None:
        pass

    def step(self, time: float, step: float) -> None:
        pass

    def get_outputs(self) -> dict[str, float]:
        return {"y": self.value}


def test_initial_outputs_follow_connected_inputs_through_a_chain() -> None:
    """Two segments in initialisation mode, the first fed by the second's pressure, the second
    by a constant piston position: listed against the chain's order, the start values need two
    passes; afterwards each initial pressure is that of its connected piston position."""
    from hil.cosim import FmuParticipant
    from hil.fmu.slave import FmuSlave

    first = FmuSlave("FeaSegment", "first", exit_initialization=False)
    second = FmuSlave("FeaSegment", "second", exit_initialization=False)
    try:
        links = [
            Connection("second.p_a", "first.x_piston", gain=-1e-6, offset=0.03),
            Connection("source.y", "second.x_piston"),
        ]
        parts = [FmuParticipant(first), FmuParticipant(second), Constant("source", 0.04)]
        master = Algorithm(parts, links, 1e-3)
        assert not first.initializing and not second.initializing
        for name in ("first", "second"):
            x = master.inputs_of(name)["x_piston"]
            alone = FmuSlave("FeaSegment", "alone", {"x_piston": x})
            try:
                assert master.values[f"{name}.p_a"] == pytest.approx(alone.get("p_a"), rel=1e-12)
            finally:
                alone.close()
        assert master.inputs_of("first")["x_piston"] != pytest.approx(0.03)  # two passes made
    finally:
        first.close()
        second.close()
