"""The golden CAN log (tests/golden/default.log): the plant, fed only the frames it received in
that run, must write the same log byte for byte: every frame it sent, their order (send phases,
rig order), their bytes, the direction flags and the timestamps (start instant + simulation time).

Regenerating the golden file is a deliberate act (`python -m tests.golden --regenerate`); no test
writes it.
"""

from __future__ import annotations

from pathlib import Path

import can
import pytest

from hil.scenario import load_scenario
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
    from hil.robots import robot_kind

    scenario = load_scenario(write_scenario(tmp_path))
    config = robot_kind(scenario.robot.kind).controller_config(scenario)
    result = replay_controller(DEFAULT_LOG.with_suffix(suffix), config)
    assert result.ok, f"{len(result.divergences)} divergences; first: {result.divergences[0]}"
    assert result.cycles == round(DURATION / 0.01) + 1
    assert result.frames_compared == 2 * round(DURATION / 0.01)
