"""Tests for hil.scenario: the built-in default, and one clear line for every malformed scenario.

Each error case starts from a minimal scenario that loads (checked below), adds or changes one
thing, and expects a `ScenarioError` whose message is a single line naming the file, the dotted
key and the reason.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import replace
from pathlib import Path

import pytest

from hil.errors import HilError
from hil.fmu.build import build_fmu
from hil.scenario import (
    DEFAULT_SCENARIO,
    Scenario,
    ScenarioError,
    load_scenario,
    resolve_scenario,
)

MINIMAL = 'name = "t"\nseed = 1\nduration = 1.0\n'


def write(tmp_path: Path, text: str, name: str = "scenario.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def error_line(path: Path) -> str:
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    message = str(info.value)
    assert "\n" not in message
    assert isinstance(info.value, HilError)
    return message


def test_default_scenario_loads() -> None:
    scenario = load_scenario()
    assert scenario.source == str(DEFAULT_SCENARIO)
    assert scenario.name == "default"
    assert scenario.seed == 1
    assert scenario.duration == 10.0
    assert (scenario.cycles, scenario.control_ticks) == (1000, 10)
    assert (scenario.camera_ticks, scenario.latency_ticks) == (10, 6)
    assert scenario.robot.base == (0.0, 0.0, math.pi / 2)
    assert scenario.task.steps[1] == (0.5, 10.0)
    assert scenario.task.sine is not None and scenario.task.sine.frequency == 0.5


def test_minimal_scenario_loads_with_defaults(tmp_path: Path) -> None:
    scenario = load_scenario(write(tmp_path, MINIMAL))
    assert (scenario.name, scenario.seed, scenario.duration) == ("t", 1, 1.0)
    assert scenario.source == str(tmp_path / "scenario.toml")
    assert (scenario.cycles, scenario.control_ticks, scenario.camera_ticks) == (100, 10, 10)
    assert scenario.bus.kind == "loopback"


def test_seed_override_replaces_the_seed(tmp_path: Path) -> None:
    default = load_scenario()
    overridden = load_scenario(seed=12345)
    assert overridden.seed == 12345
    assert replace(overridden, seed=default.seed) == default
    assert load_scenario(write(tmp_path, MINIMAL), seed=0).seed == 0


def test_a_scenario_with_connections_and_parameters_loads(tmp_path: Path) -> None:
    text = MINIMAL + (
        "[robot]\nsegments = 2\nsegment = { length = 0.05 }\n"
        '[[connections]]\nfrom = "segment1.kappa"\nto = "segment2.tau_ext"\ngain = 0.5\n'
    )
    scenario = load_scenario(write(tmp_path, text))
    assert scenario.robot.segment == {"length": 0.05}
    assert len(scenario.connections) == 1
    connection = scenario.connections[0]
    assert (connection.source, connection.target, connection.gain, connection.offset) == (
        "segment1.kappa",
        "segment2.tau_ext",
        0.5,
        0.0,
    )


CASES: dict[str, tuple[str, str, str]] = {
    # id: (scenario text, dotted key, reason)
    "unknown top-level key": (MINIMAL + 'colour = "red"\n', "colour", "unknown key (allowed: "),
    "unknown nested key": (MINIMAL + "[camera]\nfps = 30\n", "camera.fps", "unknown key"),
    "wrong type": ('name = "t"\nseed = 1\nduration = "ten"\n', "duration", "must be a number"),
    "bool for a number": ('name = "t"\nseed = 1\nduration = true\n', "duration", "got true"),
    "bool for an integer": ('name = "t"\nseed = true\nduration = 1.0\n', "seed", "an integer"),
    "float for an integer": ('name = "t"\nseed = 1.5\nduration = 1.0\n', "seed", "an integer"),
    "missing seed": ('name = "t"\nduration = 1.0\n', "seed", "missing required key"),
    "missing sine amplitude": (
        MINIMAL + "[task]\nsine = { start = 1.0, frequency = 1.0 }\n",
        "task.sine.amplitude",
        "missing required key",
    ),
    "table expected": (MINIMAL + "robot = 5\n", "robot", "must be a table"),
    "tuple length": (MINIMAL + "[robot]\nbase = [0.0, 0.0]\n", "robot.base", "3 elements"),
    "missing FMU file": (
        MINIMAL + '[robot]\nsegment_fmu = "nope.fmu"\n',
        "robot.segment_fmu",
        "nope.fmu' does not exist",
    ),
    "unknown model": (
        MINIMAL + '[robot]\ncylinder_fmu = "NoSuchModel"\n',
        "robot.cylinder_fmu",
        "unknown FMU model 'NoSuchModel'",
    ),
    "unknown FMU parameter": (
        MINIMAL + "[robot.segment]\nbogus = 1.0\n",
        "robot.segment.bogus",
        "no such parameter (parameters: length, mass,",
    ),
    "non-numeric FMU parameter": (
        MINIMAL + '[robot.cylinder]\nstroke = "long"\n',
        "robot.cylinder.stroke",
        "must be a number",
    ),
    "control period not a multiple of step": (
        MINIMAL + "[timing]\nstep = 0.001\ncontrol_period = 0.0125\n",
        "timing.control_period",
        "0.0125 s is not an integer multiple of timing.step = 0.001 s",
    ),
    "duration not a multiple of the control period": (
        'name = "t"\nseed = 1\nduration = 1.005\n',
        "duration",
        "not an integer multiple of timing.control_period",
    ),
    "camera period not a multiple of step": (
        MINIMAL + "[camera]\nrate = 300.0\n",
        "camera.rate",
        "period 0.00333333 s is not an integer multiple of timing.step",
    ),
    "latency not a multiple of step": (
        MINIMAL + "[camera]\nlatency = 0.0065\n",
        "camera.latency",
        "0.0065 s is not an integer multiple of timing.step",
    ),
    "decimation not dividing the control period": (
        MINIMAL + "[robot]\nsegment_decimation = 3\n",
        "robot.segment_decimation",
        "must divide the control period's 10 ticks",
    ),
    "too many segments": (MINIMAL + "[robot]\nsegments = 9\n", "robot.segments", "1..8"),
    "task step beyond reach": (
        MINIMAL + "[task]\nsteps = [[0.0, 0.0], [0.5, 30.0]]\n",
        "task.steps[1]",
        "curvature 30 1/m for segment 1 is beyond the reachable 26.7 1/m",
    ),
    "task sine beyond reach": (
        MINIMAL
        + "[task]\nsine = { start = 0.0, amplitude = 20.0, frequency = 1.0, offset = -8.0 }\n",
        "task.sine",
        "curvature 28 1/m for segment 1 is beyond the reachable",
    ),
    "decreasing step times": (
        MINIMAL + "[task]\nsteps = [[0.5, 0.0], [0.2, 1.0]]\n",
        "task.steps",
        "step times must be strictly increasing",
    ),
    "equal step times": (
        MINIMAL + "[task]\nsteps = [[0.5, 0.0], [0.5, 1.0]]\n",
        "task.steps",
        "step times must be strictly increasing",
    ),
    "negative seed": (
        MINIMAL.replace("seed = 1", "seed = -1"),
        "seed",
        "must not be negative",
    ),
    "source is not a user key": (
        MINIMAL + 'source = "elsewhere.toml"\n',
        "source",
        "unknown key",
    ),
    "bad bus kind": (
        MINIMAL + '[bus]\nkind = "can0"\n',
        "bus.kind",
        "must be one of loopback, virtual, config, ",
    ),
    "bad policy": (
        MINIMAL + '[controller]\npolicy = "yolo"\n',
        "controller.policy",
        "must be one of strict, hold",
    ),
    "empty task targets": (
        MINIMAL + '[robot]\nsegments = 2\n[task]\nkind = "point_to_point"\ntargets = []\n',
        "task.targets",
        "must not be empty (leave it out to draw task.count targets from the seed)",
    ),
    "empty task paths": (
        MINIMAL + '[robot]\nsegments = 2\n[task]\nkind = "path"\npaths = []\n',
        "task.paths",
        "must not be empty",
    ),
    "connection without its to": (
        MINIMAL + '[[connections]]\nfrom = "segment1.kappa"\n',
        "connections[0].to",
        "missing required key",
    ),
    "connection naming its end by the Python field": (
        MINIMAL + '[[connections]]\nsource = "segment1.kappa"\nto = "cylinder1.x"\n',
        "connections[0].source",
        "unknown key (allowed: from, to, gain, offset)",
    ),
    "a connection's from at the top level": (
        MINIMAL.replace("seed", 'from = "other.toml"\nseed', 1),
        "from",
        "unknown key (allowed: name, seed, duration,",
    ),
    "connection to a participant that does not exist": (
        MINIMAL + '[[connections]]\nfrom = "segment1.kappa"\nto = "segment2.tau_ext"\n',
        "connections[0].to",
        "'segment2.tau_ext': no participant 'segment2' (participants: camera, cylinder1, drive1,",
    ),
}


@pytest.mark.parametrize(("text", "key", "reason"), CASES.values(), ids=CASES.keys())
def test_problem_gives_one_line_with_file_key_and_reason(
    tmp_path: Path, text: str, key: str, reason: str
) -> None:
    path = write(tmp_path, text)
    message = error_line(path)
    assert message.startswith(f"{path}: {key}: ")
    assert reason in message


def test_the_reach_limit_follows_the_segment_parameters(tmp_path: Path) -> None:
    # 30 1/m is out of reach of a 0.06 m segment, within reach of a 0.05 m one (1.6/0.05 = 32)
    steps = "[task]\nsteps = [[0.0, 30.0]]\n"
    short = load_scenario(write(tmp_path, MINIMAL + "[robot.segment]\nlength = 0.05\n" + steps))
    assert short.task.steps == ((0.0, 30.0),)
    message = error_line(write(tmp_path, MINIMAL + steps, "short.toml"))
    assert "beyond the reachable 26.7 1/m" in message


def test_unknown_key_lists_the_allowed_keys(tmp_path: Path) -> None:
    message = error_line(write(tmp_path, MINIMAL + "[timing]\nsteps = 0.001\n"))
    assert message.endswith("timing.steps: unknown key (allowed: step, control_period)")


def test_unknown_connection_key_lists_every_allowed_key(tmp_path: Path) -> None:
    text = (
        MINIMAL + '[[connections]]\nfrom = "segment1.kappa"\nto = "cylinder1.x_ref"\ngian = 2.0\n'
    )
    message = error_line(write(tmp_path, text))
    assert message.startswith(f"{tmp_path / 'scenario.toml'}: connections[0].gian: unknown key")
    assert message.endswith("(allowed: from, to, gain, offset)")


def test_fmu_file_is_found_relative_to_the_scenario(tmp_path: Path) -> None:
    shutil.copy(build_fmu("FeaSegment").path, tmp_path / "mine.fmu")
    scenario = load_scenario(write(tmp_path, MINIMAL + '[robot]\nsegment_fmu = "mine.fmu"\n'))
    assert scenario.robot.segment_fmu == "mine.fmu"
    (tmp_path / "corrupt.fmu").write_bytes(b"PK")
    message = error_line(
        write(tmp_path, MINIMAL + '[robot]\nsegment_fmu = "corrupt.fmu"\n', "c.toml")
    )
    assert "robot.segment_fmu: " in message and "corrupt.fmu: not a readable FMU" in message
    message = error_line(
        write(tmp_path, MINIMAL + '[robot]\nsegment_fmu = "other.fmu"\n', "b.toml")
    )
    assert f"'{tmp_path / 'other.fmu'}' does not exist" in message


def test_invalid_toml_syntax(tmp_path: Path) -> None:
    path = write(tmp_path, 'name = "t"\nseed = \nduration = 1.0\n')
    message = error_line(path)
    assert message.startswith(f"{path}: not valid TOML: ")
    assert "line 2" in message


def test_nonexistent_scenario_file(tmp_path: Path) -> None:
    path = tmp_path / "absent.toml"
    assert error_line(path) == f"{path}: no such scenario file"


def test_a_directory_is_not_a_scenario_file(tmp_path: Path) -> None:
    message = error_line(tmp_path)
    assert message.startswith(f"{tmp_path}: cannot read: ")
    # as hil run's argument: said to be a folder (it was "no such scenario file")
    with pytest.raises(ScenarioError) as error:
        resolve_scenario(tmp_path)
    assert str(error.value) == f"{tmp_path}: is a folder; name a scenario file (.toml) in it"


def test_scenario_is_frozen() -> None:
    scenario = load_scenario()
    assert isinstance(scenario, Scenario)
    with pytest.raises(AttributeError):
        scenario.seed = 2  # type: ignore[misc]


@pytest.mark.parametrize(
    ("text", "key", "reason"),
    [
        (
            "[robot.segment]\nlength = 0.0\n",
            "robot.segment.length",
            "0 is outside the allowed range [0.0001, inf]",
        ),
        ("[robot.cylinder]\nsubstep = 0.0\n", "robot.cylinder.substep", "is outside the allowed"),
        (
            "[robot.cylinder]\nstroke = 0.06\nx_start = 0.07\n",
            "robot.cylinder.x_start",
            "must lie within the stroke [0, 0.06] m",
        ),
        (
            "[robot.cylinder]\nstroke = 0.2\nx_start = 0.1\n",
            "robot.cylinder.stroke",
            "beyond the 0.1 m that DriveStatus/DriveCommand can carry",
        ),
        (
            "[robot.segment]\nstroke = 0.06\n",
            "robot.segment.stroke",
            "the gas circuit takes the drive cylinder's geometry",
        ),
        (
            "[robot]\nsegments = 6\n[robot.segment]\nlength = 0.12\n",
            "robot",
            "beyond the camera's +-0.6 m",
        ),
        ("[camera]\nlatency = 0.7\n", "camera.latency", "must be below 0.49 s"),
        (
            '[[connections]]\nfrom = "segment1.kappa"\nto = "cylinder1.nothing"\n',
            "connections[0].to",
            "cylinder1 has no input 'nothing'",
        ),
        ("[controller]\nkp = -1.0\n", "controller.kp", "must not be negative"),
        (
            "[safety]\ncommand_timeout = 0.01\n",
            "safety.command_timeout",
            "at least two control periods",
        ),
        ('name = "../outside"\n', "name", "use letters, digits"),
    ],
)
def test_parameters_geometry_and_protocol_ranges_are_checked_before_running(
    tmp_path: Path, text: str, key: str, reason: str
) -> None:
    base = MINIMAL if not text.startswith("name") else MINIMAL.replace('name = "t"\n', "")
    path = write(tmp_path, base + text)
    message = error_line(path)
    assert message.startswith(f"{path}: {key}: "), message
    assert reason in message


def test_negative_seed_override_names_the_option() -> None:
    with pytest.raises(ScenarioError, match=r"^--seed: must not be negative, got -1$"):
        load_scenario(seed=-1)


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["bus", "load", "fish-swim"], "fish-swim: bus load"),
        (["tune", "fish-swim"], "hil tune applies to planar-arm scenarios"),
        (["replay", "missing.log", "--scenario", "planar-path"], "missing.log: no such log file"),
    ],
)
def test_every_command_taking_a_scenario_takes_a_built_in_name(
    argv: list[str],
    expected: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """As `hil run` and `hil batch`: NAME or FILE (hil tune and hil bus load said 'default: no
    such scenario file'); the command gets past the scenario to its own work or error."""
    from hil.cli import main

    monkeypatch.chdir(tmp_path)
    main(argv)
    out, err = capsys.readouterr()
    assert expected in out + err and "no such scenario" not in err, (out, err)


def test_the_default_scenario_shows_every_section() -> None:
    """The README says default.toml shows every section: each table of a scenario is there,
    as a table or (with its defaults) as a commented one."""
    import typing
    from dataclasses import fields, is_dataclass

    text = DEFAULT_SCENARIO.read_text()
    hints = typing.get_type_hints(Scenario)
    tables = [f.name for f in fields(Scenario) if is_dataclass(hints[f.name]) or f.name == "robot"]
    assert "recording" in tables and "task" in tables
    for name in tables:
        assert f"\n[{name}]" in text or f"\n# [{name}]" in text, name


@pytest.mark.parametrize("where", ["before", "after"])
def test_debug_shows_the_trace_before_or_after_the_command(tmp_path: Path, where: str) -> None:
    """`hil --debug run x` and `hil run x --debug` (it was an unrecognised argument) both raise
    the error with its trace; without it the error is one line."""
    from hil.cli import main

    absent = str(tmp_path / "absent.toml")
    argv = ["--debug", "run", absent] if where == "before" else ["run", absent, "--debug"]
    with pytest.raises(ScenarioError, match="no such scenario file"):
        main(argv)
    assert main(["run", absent]) == 1
