"""The scenario schema (hil.schema, hil.sections, the robot kinds' sections) and the reference
written from it: the committed docs/scenario-keys.md is current and names every key, and the
one-line messages generated from the declarations name the file, the key, the rule and the
value: a range (each bound inclusive or exclusive as declared), a type, a choice, a rule
between keys (in its direction), an unknown key."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil.errors import ScenarioError
from hil.rig import known_kinds, robot_kind
from hil.scenario import Scenario, load_scenario, resolve_scenario
from hil.scenario_reference import reference
from hil.schema import keys_of
from rigbus.robots import BUILT_IN

ROOT = Path(__file__).resolve().parents[1]
MINIMAL = 'name = "t"\nseed = 1\nduration = 1.0\n'


def said(tmp_path: Path, text: str) -> str | None:
    """What loading `text` says after the file's name (None: it loads)."""
    path = tmp_path / "s.toml"
    path.write_text(text)
    try:
        load_scenario(path)
    except ScenarioError as error:
        message = str(error)
        assert "\n" not in message and message.startswith(f"{path}: "), message
        return message.removeprefix(f"{path}: ")
    return None


def test_the_committed_reference_is_current() -> None:
    committed = (ROOT / "docs" / "scenario-keys.md").read_text()
    current = reference(sorted(BUILT_IN))  # the built-in kinds: a plug-in installed adds its own
    assert committed == current, "regenerate it: hil scenarios --keys > docs/scenario-keys.md"


def test_hil_scenarios_keys_prints_the_reference(capsys: pytest.CaptureFixture[str]) -> None:
    from hil.cli import main

    assert main(["scenarios", "--keys"]) == 0
    assert capsys.readouterr().out == reference()


def test_every_key_is_in_the_reference() -> None:
    text = reference()
    hints = {"timing", "bus", "camera", "safety", "controller", "task", "recording"}
    names = [k.toml_name for k in keys_of(Scenario) if k.toml_name not in {*hints, "robot"}]
    names += [f"{k.toml_name}" for k in keys_of(Scenario) if k.toml_name in hints]
    for section in hints:
        cls = next(k.hint for k in keys_of(Scenario) if k.toml_name == section)
        names += [f"{section}.{k.toml_name}" for k in keys_of(cls)]
    names += ["task.sine.frequency", "connections[i].from"]
    for kind in known_kinds():
        spec = robot_kind(kind).spec_class
        names += [f"robot.{k.toml_name}" for k in keys_of(spec)]
        for table in spec.TABLES:
            names += [f"{table.path}.{k.name}" for k in table.keys]
    missing = [n for n in names if n != "source" and f"`{n}`" not in text and f"[{n}]" not in text]
    assert not missing
    assert "`source`" not in text  # the file's own path is no key
    assert "| `d_nozzle` | m | [1e-06, 0.005] |" in text  # an FMU table's parameter, its range
    assert "| `k_bend` | N.m/rad | [0, inf] | 0.02 |" in text  # the gripper's own default


@pytest.mark.parametrize(
    ("text", "message"),
    [
        # ranges: each bound inclusive or exclusive as declared, the unit and the source named
        ("[camera]\ndropout = 1.0\n", None),
        ("[camera]\ndropout = 1.5\n", "camera.dropout: must be in [0, 1], got 1.5"),
        ("[camera]\ndropout = -0.1\n", "camera.dropout: must be in [0, 1], got -0.1"),
        ("[task]\nmargin = 1.0\n", None),
        ("[task]\nmargin = 0.0\n", "task.margin: must be in (0, 1], got 0"),
        ("[timing]\nstep = 0.2\n", "timing.step: must be in [1e-06, 0.1] s, got 0.2"),
        ("[bus]\nport = 65535\n", None),
        ("[bus]\nport = 65536\n", "bus.port: must be 0..65535, got 65536"),
        ("[bus]\nport = -1\n", "bus.port: must be 0..65535, got -1"),
        ("[bus]\nbitrate = 1000000\n", None),
        ("[bus]\nbitrate = 0\n", "bus.bitrate: must be 1..1000000 bit/s (classical CAN), got 0"),
        ("[controller]\ntimeout = 3600.0\n", None),
        ("[controller]\ntimeout = 0.0\n", "controller.timeout: must be in (0, 3600] s, got 0"),
        ("[controller]\ntorque_std = 0.0\n", "controller.torque_std: must be positive, got 0"),
        ("[controller]\nkp = -0.5\n", "controller.kp: must not be negative, got -0.5"),
        (
            "[safety]\nmax_pressure = 1e9\n",
            "safety.max_pressure: must be in (0, 300000] Pa (the DBC's DriveStatus1.p_a range "
            "= 300000), got 1e+09",
        ),
        ("[robot]\nsegments = 8\nsegment = { length = 0.05 }\n", None),
        (
            "[robot]\nsegments = 9\n",
            "robot.segments: must be 1..8 (a marker each and the gripper's drive after them), "
            "got 9",
        ),
        (
            "[robot]\nsegment_decimation = 0\n",
            "robot.segment_decimation: must be at least 1, got 0",
        ),
        # ranges bounded by other keys: the bound's value, and what it is
        ("[controller]\ncrossover = 50.0\n", None),
        (
            "[controller]\ncrossover = 50.5\n",
            "controller.crossover: must be in (0, 50] Hz (the control loop's Nyquist rate), "
            "got 50.5",
        ),
        ("[camera]\njitter = 0.0099\n", None),
        (
            "[camera]\njitter = 0.01\n",
            "camera.jitter: must be in [0, 0.01) s (the frame period 1 / camera.rate), got 0.01",
        ),
        ("[safety]\ncommand_timeout = 0.02\n", None),
        (
            "[safety]\ncommand_timeout = 0.019\n",
            "safety.command_timeout: must be in [0.02, 3600] s (at least two control periods), "
            "got 0.019",
        ),
        ("[task]\nsettle_time = 5.9\n", None),
        (
            "[task]\nsettle_time = 6.0\n",
            "task.settle_time: must be in (0, 6) s (task.max_time = 6), got 6",
        ),
        ("[task]\nsettle_time = 6.0\nmax_time = 7.0\n", None),  # the rule's direction
        (
            "[task]\ntask_gain = 100.0\n",
            "task.task_gain: must be in [0, 100) 1/s (its product with timing.control_period "
            "stays below 1), got 100",
        ),
        (
            "[task]\nsine = { start = 0.1, amplitude = 1.0, frequency = 50.0 }\n",
            "task.sine.frequency: must be in (0, 50) Hz (the control loop's Nyquist rate), got 50",
        ),
        (
            "[camera]\nrate = 50.0\n[task]\n"
            "sine = { start = 0.1, amplitude = 1.0, frequency = 25.0 }\n",
            "task.sine.frequency: must be below 25 Hz (the camera's Nyquist rate), got 25",
        ),
        (
            "[controller]\nki = 1e12\n",
            "controller.ki: must be at most 1000 m per (1/m) s (the DBC's whole piston range per "
            "0.01 1/m of curvature error per control period = 1000), got 1e+12",
        ),
        # types, choices and patterns
        ("[bus]\nport = 80.0\n", "bus.port: must be an integer, got 80.0"),
        ('[camera]\nrate = "fast"\n', "camera.rate: must be a number, got 'fast'"),
        ("[bus]\nallow_remote = 1\n", "bus.allow_remote: must be true or false, got 1"),
        (
            '[camera]\nocclusion_scope = "half"\n',
            "camera.occlusion_scope: must be one of frame, marker, got 'half'",
        ),
        (
            '[bus]\nchannel = "my bus"\n',
            "bus.channel: must be a name without spaces or '<>', not empty, got 'my bus'",
        ),
        # rules between keys: when, unless, and the multiple
        (
            "[camera]\nocclusion_interval = 1.0\n",
            "camera.occlusion_duration: must be positive when camera.occlusion_interval is "
            "positive, got 0",
        ),
        ("[camera]\nocclusion_interval = 1.0\nocclusion_duration = 0.1\n", None),
        (
            '[bus]\nhost = "0.0.0.0"\n',
            "bus.host: must be one of 127.0.0.1, localhost, ::1 unless bus.allow_remote is true "
            "(softhil stays on the loopback unless told), got '0.0.0.0'",
        ),
        (
            "[timing]\ncontrol_period = 0.0105\n",
            "timing.control_period: 0.0105 s is not an integer multiple of timing.step = 0.001 s",
        ),
        (
            '[robot]\nsegments = 2\n[task]\nkind = "pipe"\n',
            "task.goal: must be given when task.kind is 'pipe' (the goal [x, y] deep in the "
            "channel)",
        ),
        (
            '[robot]\nsegments = 2\n[task]\nkind = "pipe"\ngoal = [0.1, 0.1]\n'
            "centreline = [[0.0, 0.0]]\n",
            "task.centreline: must have at least 2 points when task.kind is 'pipe' (the "
            "channel's centreline), got 1",
        ),
        # unknown keys, in a section and in a table the robot kind declares
        ("[timing]\nsteps = 0.001\n", "timing.steps: unknown key (allowed: step, control_period)"),
        (
            "[robot.environment]\nwidth = 0.02\n[robot.gripper]\nfinger_lenght = 0.04\n",
            "robot.gripper.finger_lenght: unknown key (allowed: finger_length, finger_width, "
            "root_offset, grasp_offset, theta_open, theta_closed, segment, cylinder)",
        ),
    ],
)
def test_the_generated_message(tmp_path: Path, text: str, message: str | None) -> None:
    assert said(tmp_path, MINIMAL + text) == message


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            ("step = 0.001", "step = 0.002"),
            "timing.step: must be at most 0.001 s (the fish's valves), got 0.002",
        ),
        (
            ("open_time = 0.06", "open_time = -0.01"),
            "robot.valve.open_time: must be in [0, 1] s (the DBC's ValveCommand1.open_time "
            "range = 1), got -0.01",
        ),
        (
            ("side = 1", "side = 3"),
            "robot.side: must be one of 1 (channel a, turn left), 2 (channel b, turn right), got 3",
        ),
        (("side = 1", "side = 1\nduty = 1.0"), None),
        (("side = 1", "side = 1\nduty = 0.0"), "robot.duty: must be in (0, 1], got 0"),
    ],
)
def test_the_fish_s_generated_message(
    tmp_path: Path, edit: tuple[str, str], message: str | None
) -> None:
    text = resolve_scenario("fish-escape").read_text()
    assert edit[0] in text
    assert said(tmp_path, text.replace(edit[0], edit[1], 1)) == message


def test_a_gripper_table_is_read_with_its_rules(tmp_path: Path) -> None:
    """theta_open below theta_closed: the rule's direction, with the bound's value."""
    text = resolve_scenario("planar-grasp").read_text()
    assert "[robot.gripper]\n" in text
    bad = text.replace("[robot.gripper]\n", "[robot.gripper]\ntheta_open = 1.35\n", 1)
    assert said(tmp_path, bad) == (
        "robot.gripper.theta_open: must be below 1.35 rad (robot.gripper.theta_closed = 1.35), "
        "got 1.35"
    )
    wrong = text.replace("[robot.gripper]\n", '[robot.gripper]\nfinger_width = "thin"\n', 1)
    assert said(tmp_path, wrong) == "robot.gripper.finger_width: must be a number, got 'thin'"
