"""The Environment FMU in the planar-arm rig (issue 12): contact acts on the simulated arm."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controllers import kinematics
from hil.errors import ScenarioError
from hil.rig import build_rig
from hil.run import RunOptions, run_scenario
from hil.scenario import load_scenario
from hil.summary import read_signals

WALL_X = 0.05
SCENARIO = f"""
name = "wall"
seed = 1
duration = 2.0
[robot]
segments = 3
actuator = "cylindrical"
[robot.environment]
walls = [[[{WALL_X}, -0.1], [{WALL_X}, 0.4]]]
[camera]
noise = 0.0
dropout = 0.0
outlier_rate = 0.0
[task]
steps = [[0.0, 0.0], [0.3, -15.0]]
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def wall_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, dict]:
    tmp = tmp_path_factory.mktemp("wall")
    scenario = load_scenario(write(tmp, SCENARIO))
    options = RunOptions(out=tmp / "run", inprocess=True, progress=False, reports=False)
    summary = run_scenario(scenario, options)
    return summary.summary, read_signals(tmp / "run" / "signals.csv")


def test_a_wall_stops_the_arm_it_would_bend_through(wall_run) -> None:
    """Commanded to -15 1/m, the free arm's tip would reach x ~ 0.08 m; the wall at 0.05 m holds
    it, the segments feel the torque, and the penetration stays at the contact stiffness' scale."""
    summary, s = wall_run
    free_tip = kinematics.forward([-15.0] * 3, [0.06] * 3, (0.0, 0.0, np.pi / 2))[-1, 0]
    assert free_tip > WALL_X + 0.02
    kappas = np.column_stack([s[f"kappa_{n}"] for n in (1, 2, 3)])
    backbone_x = [
        kinematics.backbone(k, [0.06] * 3, (0.0, 0.0, np.pi / 2))[:, 0].max() for k in kappas
    ]
    radius = 0.008  # the cylindrical actuator's 16 mm backbone width / 2
    assert max(backbone_x) < WALL_X - radius + 2e-3
    assert np.nanmax([s[f"penetration_{n}"] for n in (1, 2, 3)]) < 2e-3
    assert np.nanmax(s["contact_force_3"]) > 0.0
    assert s["tau_ext_1"][-1] != 0.0  # the contact's torque reaches the base segment
    assert summary["steady_state_error"] > 1.0  # it could not track through the wall


def test_contact_never_adds_energy_to_the_arm(wall_run) -> None:
    _, s = wall_run
    assert np.all(np.diff(s["E_dissipated_env"]) >= -1e-12)
    assert np.nanmax(s["W_arm_env"]) <= 1e-6  # the environment only takes energy from the arm


def test_no_environment_section_no_environment_fmu(tmp_path: Path) -> None:
    text = SCENARIO.split("[robot.environment]")[0] + "[camera]" + SCENARIO.split("[camera]")[1]
    rig = build_rig(load_scenario(write(tmp_path, text)))
    try:
        names = {getattr(p, "name", "") for p in rig.participants}
        assert not any("environment" in n for n in names)
        assert not any(c.source.startswith("environment") for c in rig.connections)
    finally:
        rig.close()


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            "walls = [[[",
            "walls = [[[0, 0], [1, 1]], [[0, 1], [1, 2]], [[",
            r"walls: a list of at most 2",
        ),
        (f"[{WALL_X}, -0.1]", "[0.05]", r"walls\[0\]\[0\]: must be \[x, y\]"),
        (
            "[robot.environment]",
            "[robot.environment]\nlength_1 = 0.1",
            r"length_1: set by the robot",
        ),
        ("[robot.environment]", "[robot.environment]\nk_contact = -5.0", r"k_contact"),
        (
            "[robot.environment]",
            "[robot.environment]\nobjects = [{ x = 0.1, y = 0.1, colour = 3 }]",
            r"objects\[0\]\.colour: unknown key",
        ),
        (
            'actuator = "cylindrical"',
            'actuator = "octagonal"',
            r"robot\.actuator: must be one of rectangular, cylindrical, got 'octagonal'",
        ),
    ],
)
def test_environment_keys_are_checked(tmp_path: Path, old: str, new: str, message: str) -> None:
    assert old in SCENARIO
    with pytest.raises(ScenarioError, match=message) as caught:
        load_scenario(write(tmp_path, SCENARIO.replace(old, new, 1)))
    assert "\n" not in str(caught.value)


def test_cylindrical_set_applies_under_the_scenario_values(tmp_path: Path) -> None:
    from robots.planar_arm.plant.rig import ROBOT

    text = SCENARIO.replace(
        "[robot.environment]", "[robot.segment]\nk_bend = 0.05\n[robot.environment]"
    )
    params = ROBOT.parameters(load_scenario(write(tmp_path, text)), "segment")
    assert params[0]["theta_max"] == 1.2 and params[0]["G_a"] == 7.0e-7  # from the set
    assert params[0]["k_bend"] == 0.05  # the scenario's value wins


@pytest.mark.parametrize("pipe", [2, 4])
def test_pipe_is_traversed_to_its_goal_without_penetrating(tmp_path: Path, pipe: int) -> None:
    """Whole-arm planning through a shipped pipe section (one bend; the tight bend) with the
    realistic camera: the tip reaches the goal, the walls are never penetrated by 2 mm."""
    from hil.scenario import resolve_scenario

    text = resolve_scenario(f"planar-pipe-{pipe}").read_text()
    path = write(tmp_path, text.replace("duration = 8.0", "duration = 5.5"))
    summary = run_scenario(
        load_scenario(path), RunOptions(out=tmp_path / "run", inprocess=True, progress=False)
    ).summary
    assert summary["goal_reached"] is True and summary["time_to_goal"] < 5.0
    assert summary["goal_error"] < 2e-3
    assert summary["penetration_max"] < 2e-3
    assert summary["contact_impulse"] >= 0.0
    assert summary["warnings"] == [] and summary["controller"]["notes"] == []


def test_a_pipe_plan_that_relaxes_its_clearance_says_so_in_the_summary(tmp_path: Path) -> None:
    """A clearance the pipe cannot give (50 mm from each wall of a 50 mm pipe): the planner
    relaxes it (a collision tolerated) and the run's summary warns, as the README promises."""
    from hil.scenario import resolve_scenario

    text = resolve_scenario("planar-pipe-1").read_text()
    text = text.replace("duration = 8.0", "duration = 1.0").replace(
        "clearance = 0.002", "clearance = 0.05"
    )
    summary = run_scenario(
        load_scenario(write(tmp_path, text)),
        RunOptions(out=tmp_path / "run", inprocess=True, progress=False),
    ).summary
    note = (
        "the pipe plan cannot keep the 50 mm clearance from the walls at 6 of its 6 steps "
        "(first: step 1) and relaxes it there"
    )
    assert summary["controller"]["notes"] == [note]
    assert summary["warnings"] == [f"controller: {note}"]


def test_a_segment_that_starts_bent_starts_at_rest(tmp_path: Path) -> None:
    """theta_start puts the piston where that bend is the static equilibrium: with the drive
    holding it there, the bend stays (it would spring back towards straight from mid-stroke)."""
    from robots.planar_arm.plant.rig import ROBOT

    text = (
        SCENARIO.split("[robot.environment]")[0]
        + "[robot.segment]\ntheta_start = [0.9, -0.6, 0.0]\n[camera]"
        + SCENARIO.split("[camera]")[1]
    ).replace(
        "[[0.0, 0.0], [0.3, -15.0]]", "[[0.0, 15.0], [0.3, 15.0]]\nscale = [1.0, -0.6667, 0.0]"
    )
    scenario = load_scenario(write(tmp_path, text))
    pistons = ROBOT.start_pistons(scenario)
    assert pistons[0] > 0.025 > pistons[1] and pistons[2] == 0.025  # bent ways, straight at mid
    rig = build_rig(scenario)
    try:
        from hil.cosim import Algorithm

        master = Algorithm(rig.participants, rig.connections, scenario.timing.step)
        start = [master.values[f"segment{n}.kappa"] for n in (1, 2)]
        # the initial outputs follow the connected inputs (the master's initialisation), not
        # the inputs' declared starts: the bent segment's pressure at t = 0 is its start's
        pressure = master.values["segment1.p_a"]
        master.advance_to(1)
        assert master.values["segment1.p_a"] == pytest.approx(pressure, rel=1e-3)
        assert pressure > 1e4
        master.advance_to(100)  # 0.1 s with the drives holding their start
        after = [master.values[f"segment{n}.kappa"] for n in (1, 2)]
    finally:
        rig.close()
    assert start == pytest.approx([15.0, -10.0], abs=1e-9)
    assert after == pytest.approx(start, abs=0.05)


def test_pipe_metrics_from_the_recorded_truth() -> None:
    """goal_reached needs the tip to enter the band and stay; penetration_max is the deepest
    penetration of any segment at any time."""
    from types import SimpleNamespace

    from robots.planar_arm.plant.tasks import _pipe

    t = np.arange(0.0, 3.0, 0.01)
    goal = (0.3, 0.0)
    approach = np.clip(1.0 - t, 0.0, None)[:, None] * np.array([0.0, 0.05])
    signals = {
        "penetration_1": np.where((t > 0.5) & (t < 0.6), 1.5e-3, 0.0),
        "penetration_2": np.full(t.size, 2e-4),
        "contact_impulse": np.linspace(0.0, 0.7, t.size),
    }
    task = SimpleNamespace(band=2e-3)
    reached = _pipe(goal, 2, t, np.array(goal) + approach, signals, task)
    assert reached["goal_reached"] is True
    assert reached["time_to_goal"] == pytest.approx(0.96, abs=0.011)  # 50 mm to 2 mm in 1 s
    assert reached["penetration_max"] == 1.5e-3
    assert reached["contact_impulse"] == pytest.approx(0.7)
    short = _pipe(goal, 2, t, np.tile(np.array(goal) + [0.0, 5e-3], (t.size, 1)), signals, task)
    assert short["goal_reached"] is False and short["time_to_goal"] is None
    assert short["goal_error"] == pytest.approx(5e-3)
    left = np.array(goal) + np.where(t[:, None] < 2.0, 0.0, 0.01) * np.array([1.0, 0.0])
    assert _pipe(goal, 2, t, left, signals, task)["goal_reached"] is False  # reached, then left


def test_an_environment_key_error_names_the_scenario_key(tmp_path: Path) -> None:
    """A key the scenario gave is named as written (robot.environment.k_contact), not as the
    FMU's parameter in parentheses."""
    from hil.errors import ScenarioError
    from hil.scenario import resolve_scenario

    text = resolve_scenario("planar-pipe-1").read_text()
    text = text.replace("[robot.environment]", "[robot.environment]\nk_contact = -5.0", 1)
    with pytest.raises(ScenarioError, match=r": robot\.environment\.k_contact: -5 is outside"):
        load_scenario(write(tmp_path, text))
