"""The golden CAN log (robots/planar_arm/golden/default.log): the plant, fed only the frames it
received in
that run, must write the same log byte for byte: every frame it sent, their order (send phases,
rig order), their bytes, the direction flags and the timestamps (start instant + simulation time).

The controller side of each golden log is replayed too (hil.replay): the robot's own controller,
configured from the log's scenario as `hil run` configures it and fed the plant's frames of the
log, must send the controller's frames of the log at the same cycles; a changed controller
parameter fails there, naming the first diverging cycle, message and signal.

Regenerating the golden file is a deliberate act (`python -m tests.golden --regenerate`); no test
writes it.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import can
import pytest

from hil.scenario import Scenario, load_scenario
from rigbus.protocol import Protocol
from tests.golden import (
    DEFAULT_LOG,
    DURATION,
    PLANT_GOLDENS,
    plant_golden,
    replay,
    write_plant_scenario,
    write_scenario,
)

START = 1433116800.0  # 2015-06-01T00:00:00Z, the default log start
RECEIVED_IDS = {0x080, 0x201, 0x381}  # SYNC, DriveCommand1, ControllerState1: the controller's


def first_difference(got: list[str], want: list[str]) -> str:
    for i, (a, b) in enumerate(zip(got, want, strict=False)):
        if a != b:
            return f"line {i + 1}: got {a!r}, golden {b!r}"
    return f"{len(got)} lines, golden has {len(want)}"


def test_plant_replays_the_golden_log_byte_for_byte(tmp_path: Path) -> None:
    scenario = load_scenario(write_scenario(tmp_path))
    out = replay(DEFAULT_LOG, scenario, tmp_path)
    got, want = out.read_text().splitlines(), DEFAULT_LOG.read_text().splitlines()
    assert got == want, first_difference(got, want)
    assert out.read_bytes() == DEFAULT_LOG.read_bytes()


@pytest.mark.parametrize("name", sorted(PLANT_GOLDENS))
def test_plant_replays_the_golden_logs_of_the_other_robots_byte_for_byte(
    tmp_path: Path, name: str
) -> None:
    """The fish's and the gripper arm's FMUs (FishBody, FishValve, GasSource; Environment with
    table, walls and objects) and device nodes, fed the frames they received, write their log
    again to the bit."""
    golden = plant_golden(name)
    scenario = load_scenario(write_plant_scenario(name, tmp_path))
    out = replay(golden, scenario, tmp_path)
    got, want = out.read_text().splitlines(), golden.read_text().splitlines()
    assert got == want, first_difference(got, want)
    assert any(line.endswith(" T") for line in want) and any(line.endswith(" R") for line in want)


def test_golden_log_is_the_plants_view_of_the_bus() -> None:
    messages = list(can.LogReader(str(DEFAULT_LOG)))
    cycles = round(DURATION / 0.01)
    syncs = [m for m in messages if m.arbitration_id == 0x080]
    assert len(syncs) == cycles + 1
    # microsecond stamps (candump), read back as float seconds since the epoch (~0.2 us steps)
    assert [m.timestamp - START for m in syncs] == pytest.approx(
        [0.01 * c for c in range(cycles + 1)], abs=5e-7
    )
    # R: what the controller sent; T: what the plant sent
    for m in messages:
        assert m.is_rx == (m.arbitration_id in RECEIVED_IDS), m
    sent = {m.arbitration_id for m in messages if not m.is_rx}
    assert sent == {0x181, 0x27F, 0x280, 0x281, 0x701}
    lines = DEFAULT_LOG.read_text().splitlines()
    assert lines[0] == "(1433116800.000000) can0 080#00 R"
    assert all(
        line.endswith(" T") == (line.split()[2][:3] not in {"080", "201", "381"}) for line in lines
    )


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_the_shipped_controller_replays_the_golden_logs(tmp_path: Path, suffix: str) -> None:
    """CAN log replay as a regression test: today's controller, configured from the shipped
    default scenario, must send exactly the recorded commands and states to the recorded plant
    frames. A change of the controller (gains, estimator, PI law) fails here, naming the first
    diverging cycle: regenerate the goldens on purpose if the change is intended."""
    from hil.replay import replay as replay_controller
    from hil.rig import robot_kind

    scenario = load_scenario(write_scenario(tmp_path))
    config = robot_kind(scenario.robot.kind).controller_config(scenario)
    result = replay_controller(DEFAULT_LOG.with_suffix(suffix), config)
    assert result.ok, f"{len(result.divergences)} divergences; first: {result.divergences[0]}"
    assert result.cycles == round(DURATION / 0.01) + 1
    assert result.frames_compared == 2 * round(DURATION / 0.01)


def logged_controller_side(log: Path) -> list[list[tuple[int, bytes]]]:
    """Read from the log's text, independently of hil.replay: per SYNC the controller sent
    (an R 080 line), the controller's frames after it (the other R lines) as (id, data)."""
    cycles: list[list[tuple[int, bytes]]] = []
    for number, line in enumerate(log.read_text().splitlines(), start=1):
        _, _, frame, direction = line.split()
        can_id, _, data = frame.partition("#")
        if direction != "R":
            continue
        if can_id == "080":
            cycles.append([])
            continue
        assert cycles, f"{log.name}: line {number}: a controller frame before the first SYNC"
        cycles[-1].append((int(can_id, 16), bytes.fromhex(data)))
    return cycles


def robot_controller(name: str, folder: Path) -> tuple[Scenario, Any]:
    """The scenario of golden `name` and its robot's controller configuration, built exactly as
    `hil run` builds it (and as the controller program reads it back from controller.json)."""
    from controllers.config import read_config
    from hil.run import controller_config

    scenario = load_scenario(write_plant_scenario(name, folder))
    config = controller_config(scenario)
    assert read_config(config.to_json()) == config  # a separate program sees the same config
    return scenario, config


@pytest.mark.parametrize("name", sorted(PLANT_GOLDENS))
def test_the_robots_own_controllers_replay_their_golden_logs(tmp_path: Path, name: str) -> None:
    """The controller side of the fish's and the gripper arm's golden logs: the robot's own
    controller, fed the plant's frames of the log, sends the controller's frames of the log, the
    same bytes (bits no signal covers too) in the same order at the same cycles."""
    from hil.replay import replay as replay_controller

    golden = plant_golden(name)
    scenario, config = robot_controller(name, tmp_path)
    assert config.robot == scenario.robot.kind
    logged = logged_controller_side(golden)
    assert len(logged) == round(PLANT_GOLDENS[name][1] / scenario.timing.control_period) + 1
    result = replay_controller(golden, config)
    assert result.ok, f"{len(result.divergences)} divergences; first: {result.divergences[0]}"
    assert result.cycles == len(logged)
    assert result.frames_compared == sum(map(len, logged)) > 0
    sent = [[(m.arbitration_id, bytes(m.data)) for m in frames] for frames in result.sent]
    for cycle, (got, want) in enumerate(zip(sent, logged, strict=True)):
        assert got == want, f"cycle {cycle}: sent {got}, logged {want}"


def first_change(
    log: Path, message: str, signal: str, value: Any = None
) -> tuple[int, float, float]:
    """(cycle, its time, the value) of the first frame `message` in `log` whose `signal` is not
    `value`, or (with `value` None) differs from the first such frame's."""
    definition = Protocol().database.get_message_by_name(message)
    cycle, start, reference = -1, None, value
    for m in can.LogReader(str(log)):
        if m.arbitration_id == 0x080:
            cycle += 1
            start = m.timestamp if start is None else start
        elif m.arbitration_id == definition.frame_id and m.is_rx:
            got = definition.decode(bytes(m.data), decode_choices=False)[signal]
            reference = got if reference is None else reference
            if got != reference:
                assert start is not None
                return cycle, m.timestamp - start, float(got)
    raise AssertionError(f"{log.name}: {message}.{signal} never changes")


def test_a_changed_valve_time_fails_the_fish_replay_at_its_first_pulse(tmp_path: Path) -> None:
    """The fish's escape pulse from a valve-open time 0.04 s instead of the run's 0.06 s: the
    replay fails at the log's first pulse command, naming its cycle, message and signal."""
    from hil.replay import assert_replays

    _, config = robot_controller("fish-escape", tmp_path)
    assert config.open_time == 0.06
    message = f"ValveCommand{config.side}"
    cycle, t, recorded = first_change(plant_golden("fish-escape"), message, "open_time", 0.0)
    assert recorded == pytest.approx(config.open_time)
    changed = dataclasses.replace(config, open_time=0.04)
    first = f"first: cycle {cycle} (t = {t:.3f} s): {message}.open_time expected 0.06, got 0.04;"
    with pytest.raises(AssertionError, match=re.escape(first)):
        assert_replays(plant_golden("fish-escape"), changed)


def test_a_changed_grasp_time_fails_the_grasp_replay_at_the_fingers_first_stroke(
    tmp_path: Path,
) -> None:
    """The gripper's strokes are spread over half the grasp time: with 0.5 s instead of 1 s the
    fingers open faster, and the replay fails at the log's first step of the opening stroke (and
    not before), naming its cycle, the gripper's drive command and its piston setpoint."""
    from hil.replay import replay as replay_controller

    _, config = robot_controller("planar-grasp", tmp_path)
    assert config.plan.grasp_time == 1.0
    message = f"DriveCommand{config.gripper.node}"
    golden = plant_golden("planar-grasp")
    cycle, t, recorded = first_change(golden, message, "piston_setpoint")
    changed = dataclasses.replace(config, plan=dataclasses.replace(config.plan, grasp_time=0.5))
    result = replay_controller(golden, changed)
    assert not result.ok
    first = result.divergences[0]
    assert (first.cycle, first.time, first.message, first.signal) == (
        cycle,
        pytest.approx(t, abs=1e-6),
        message,
        "piston_setpoint",
    )
    assert first.expected == pytest.approx(recorded, abs=1e-9)
    assert first.actual is not None and first.actual != pytest.approx(recorded, abs=1e-9)
    assert result.cycles == len(logged_controller_side(golden))
