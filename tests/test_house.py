"""The house for several robots: robot kinds by name, per-actuator parameters, logs in every
format python-can writes, the log start time, bus specs for any python-can interface, CLI
conventions."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import can
import numpy as np
import pytest

from hil.cli import main
from hil.errors import HilError, ScenarioError
from hil.rig import build_rig, known_kinds, robot_kind
from hil.run import RunOptions, run_scenario
from hil.scenario import DEFAULT_SCENARIO, load_scenario
from rigbus.canbus import BusOpenError, BusSpec, open_bus
from rigbus.protocol import GenericFrame, Protocol

START = 1433116800.0  # 2015-06-01T00:00:00Z, the documented default log start

SIX = """
name = "six"
seed = 3
duration = 0.2
[robot]
kind = "planar_arm"
segments = 6
[robot.segment]
length = [0.06, 0.05, 0.04, 0.06, 0.05, 0.04]
k_bend = 0.025
[robot.segment.2]
k_bend = 0.035
[robot.segment.3]
k_bend = 0.045
[robot.segment.5]
k_bend = 0.035
[robot.segment.6]
k_bend = 0.045
[task]
steps = [[0.0, 0.0], [0.1, 5.0]]
"""


def write(tmp_path: Path, text: str, name: str = "s.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def short_default(tmp_path: Path, extra: str = "") -> Path:
    text = DEFAULT_SCENARIO.read_text().replace("duration = 10.0", "duration = 1.0")
    return write(tmp_path, text + extra)


def run(tmp_path: Path, scenario: Path, out: str, **options: object):
    return run_scenario(
        load_scenario(scenario),
        RunOptions(out=tmp_path / out, inprocess=True, progress=False, reports=False, **options),  # type: ignore[arg-type]
    )


@pytest.fixture(scope="module")
def short_run(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    """One run of the 1 s default scenario with every default option, shared by the tests that
    only read its files (they never write into its folder); a test comparing it with another
    run makes that run itself."""
    folder = tmp_path_factory.mktemp("short")
    return run(folder, short_default(folder), "run")


def test_robot_kinds_are_found_by_name() -> None:
    assert "planar_arm" in known_kinds()
    assert robot_kind("planar_arm").name == "planar_arm"
    with pytest.raises(HilError, match="unknown robot kind 'octopus' \\(known: .*planar_arm"):
        robot_kind("octopus")


def test_unknown_robot_kind_in_a_scenario_is_one_line(tmp_path: Path) -> None:
    path = write(tmp_path, 'name = "x"\nseed = 1\nduration = 1.0\n[robot]\nkind = "octopus"\n')
    with pytest.raises(ScenarioError, match=r"s\.toml: robot\.kind: unknown robot kind 'octopus'"):
        load_scenario(path)


def test_six_segments_of_three_lengths_and_stiffnesses_each_get_their_own(tmp_path: Path) -> None:
    # SIX runs 0.2 s: the step at 0.1 s is in; what is checked is where every parameter went
    scenario = load_scenario(write(tmp_path, SIX))
    lengths = [0.06, 0.05, 0.04, 0.06, 0.05, 0.04]
    stiffness = [0.025, 0.035, 0.045, 0.025, 0.035, 0.045]
    result = run(tmp_path, tmp_path / "s.toml", "six")
    recorded = result.summary["parameters"]
    for n in range(1, 7):
        assert recorded[f"segment{n}"]["length"] == lengths[n - 1]
        assert recorded[f"segment{n}"]["k_bend"] == stiffness[n - 1]
    # the FMUs really have them: a segment's steady bend answers its own stiffness, and the
    # controller was told each segment's own length
    config = json.loads((tmp_path / "six" / "controller.json").read_text())
    assert config["lengths"] == lengths
    assert [b["k_bend"] for b in config["bends"]] == stiffness
    rig = build_rig(scenario)
    try:
        slaves = {p.name: p for p in rig.participants}
        got = [slaves[f"segment{n}"].slave.get("k_bend") for n in range(1, 7)]  # type: ignore[attr-defined]
        assert got == stiffness
    finally:
        rig.close()
    # and the camera sees markers at the true lengths: the base-to-tip chord of a straight arm
    assert result.summary["status"] == "completed"


@pytest.mark.parametrize(
    ("text", "key", "reason"),
    [
        ("length = [0.06, 0.05]", "robot.segment.length", "has 2 values for 6 segments"),
        ("length = [0.06, 0.05, 0.04, 0.06, 0.05, true]", "robot.segment.length[5]", "number"),
        ("[robot.segment.7]\nk_bend = 0.1", "robot.segment.7", "no segment 7"),
        ("bogus = 1.0", "robot.segment.bogus", "no such parameter"),
        ("[robot.segment.2]\nk_bend = -1.0", "robot.segment.2.k_bend", "outside"),
    ],
)
def test_per_actuator_parameters_are_checked(
    tmp_path: Path, text: str, key: str, reason: str
) -> None:
    base = 'name = "x"\nseed = 1\nduration = 1.0\n[robot]\nsegments = 6\n[robot.segment]\n'
    with pytest.raises(ScenarioError) as error:
        load_scenario(write(tmp_path, base + text + "\n"))
    message = str(error.value)
    assert f": {key}: " in message and reason in message
    assert "\n" not in message


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf", ".trc", ".csv", ".mf4"])
def test_can_log_in_every_format_reads_back_frame_for_frame(
    tmp_path: Path, suffix: str, short_run
) -> None:
    if suffix == ".mf4":
        pytest.importorskip("asammdf", reason="MF4 needs the optional asammdf")
    scenario = short_default(tmp_path)
    reference = short_run  # the same scenario and seed with the default candump log
    candump = list(can.LogReader(str(reference.out / "can.log")))
    result = run(tmp_path, scenario, "fmt", can_log=f"can{suffix}")
    path = result.out / f"can{suffix}"
    reader = (
        can.ASCReader(str(path), relative_timestamp=False)
        if suffix == ".asc"
        else can.LogReader(str(path))
    )
    got = list(reader)
    assert (
        len(got)
        == len(candump)
        == result.summary["frames"]["sent"] + result.summary["frames"]["received"]
    )
    resolution = {".trc": 1e-4, ".csv": 1e-6}.get(suffix, 1e-5)
    for a, b in zip(candump, got, strict=True):
        assert (a.arbitration_id, bytes(a.data)) == (b.arbitration_id, bytes(b.data))
        assert b.timestamp == pytest.approx(a.timestamp, abs=resolution)
        if suffix not in (".csv",):  # python-can's CSV has no direction column
            assert a.is_rx == b.is_rx
    # same scenario and seed, in another folder: the same bytes (the ASC header is dated from
    # the log start; the TRC header names the file, not the folder)
    if suffix in (".log", ".asc", ".blf", ".trc", ".csv"):
        # for .log the shared reference is already a second run with the same options
        again = (
            reference
            if suffix == ".log"
            else run(tmp_path, scenario, "again", can_log=f"can{suffix}")
        )  # noqa: E501
        assert (again.out / f"can{suffix}").read_bytes() == path.read_bytes()


def test_log_is_stamped_from_the_documented_start_and_a_chosen_one(
    tmp_path: Path, short_run
) -> None:
    scenario = short_default(tmp_path)
    first = next(iter(can.LogReader(str(short_run.out / "can.log"))))
    assert first.timestamp == START
    other = run(tmp_path, scenario, "b", start="2020-01-02T03:04:05Z")
    assert other.summary["log_start"] == 1577934245.0
    line = (other.out / "can.log").read_text().splitlines()[0]
    assert line.startswith("(1577934245.000000) can0 080#00 R")
    with pytest.raises(HilError, match="--start: 'yesterday' is not an ISO 8601 instant"):
        run(tmp_path, scenario, "c", start="yesterday")


def test_candump_lines_are_what_candump_writes(short_run) -> None:
    log = short_run.out / "can.log"
    import re

    pattern = re.compile(r"^\(\d{10}\.\d{6}\) can0 [0-9A-F]{3}#(?:[0-9A-F]{2}){0,8} [TR]$")
    lines = log.read_text().splitlines()
    assert lines and all(pattern.match(line) for line in lines)
    assert lines[0].endswith(" R") and lines[1].endswith(" T")  # SYNC received, heartbeat sent


@pytest.mark.skipif(shutil.which("log2asc") is None, reason="can-utils (Debian) not installed")
def test_log2asc_writes_one_header(tmp_path: Path, short_run) -> None:
    log = short_run.out / "can.log"
    out = tmp_path / "x.asc"
    subprocess.run(["log2asc", "-I", str(log), "-O", str(out), "can0"], check=True)
    text = out.read_text()
    assert text.count("date ") == 1
    assert text.startswith("date Mon Jun  1 00:00:00 2015")
    assert len(list(can.ASCReader(str(out)))) == len(log.read_text().splitlines())


def test_signals_carry_units_that_pandas_or_csv_read_in_one_call(short_run) -> None:
    out = short_run.out
    import csv

    units = {
        row["signal"]: row["unit"] for row in csv.DictReader((out / "signals.units.csv").open())
    }
    header = (out / "signals.csv").read_text().splitlines()[0].split(",")
    assert list(units) == header
    assert units["time"] == "s" and units["p_a_1"] == "Pa" and units["kappa_1"] == "1/m"
    assert units["x_1"] == "m" and units["i_motor_1"] == "A"


def test_signals_as_mf4(tmp_path: Path) -> None:
    asammdf = pytest.importorskip("asammdf", reason="MF4 needs the optional asammdf")
    out = run(tmp_path, short_default(tmp_path), "a", mf4=True).out
    mdf = asammdf.MDF(str(out / "signals.mf4"))
    p_a = mdf.get("p_a_1")
    assert p_a.unit == "Pa"
    from hil.summary import read_signals

    csv_values = read_signals(out / "signals.csv")
    assert np.array_equal(p_a.samples, csv_values["p_a_1"])


@pytest.mark.parametrize(
    ("options", "extra", "names"),
    [
        ({"mf4": True}, "", "--mf4: "),
        ({"can_log": "can.mf4"}, "", "--can-log: "),
        ({}, "\n[recording]\nmf4 = true\n", "s.toml: recording.mf4: "),
        ({}, '\n[recording]\ncan_log = "run.mf4"\n', "s.toml: recording.can_log: "),
    ],
)
def test_mf4_without_asammdf_fails_before_the_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, options: dict, extra: str, names: str
) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "asammdf", None)  # as if it were not installed
    scenario = short_default(tmp_path, extra)
    with pytest.raises(HilError) as error:
        run(tmp_path, scenario, "out", **options)
    message = str(error.value)
    assert names in message and "MF4 needs asammdf" in message and "pip install asammdf" in message
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("loopback", BusSpec("loopback", "softhil", "127.0.0.1", 29536)),
        ("loopback:4000", BusSpec("loopback", "softhil", "127.0.0.1", 4000)),
        ("virtual:x", BusSpec("virtual", "x")),
        ("socketcan:vcan0", BusSpec("socketcan", "vcan0")),
        ("pcan:PCAN_USBBUS1", BusSpec("pcan", "PCAN_USBBUS1")),
        (
            "slcan:/dev/ttyACM0,bitrate=500000",
            BusSpec("slcan", "/dev/ttyACM0", options=(("bitrate", "500000"),)),
        ),
        ("kvaser", BusSpec("kvaser", None)),
        ("config", BusSpec("config", None)),
    ],
)
def test_bus_specs_pass_any_python_can_interface_through(text: str, expected: BusSpec) -> None:
    assert BusSpec.parse(text) == expected


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("bogus:1", "neither loopback, virtual, config nor a python-can interface"),
        ("loopback:0", "port must be 1..65535"),
        ("loopback:70000", "port must be 1..65535"),
        ("loopback:x", "port must be an integer"),
        ("virtual:a b", "no spaces"),
        ("slcan:x,bitrate", "options are key=value"),
    ],
)
def test_bad_bus_specs_are_one_line(text: str, reason: str) -> None:
    with pytest.raises(ValueError, match=reason):
        BusSpec.parse(text)


@pytest.mark.parametrize(
    ("bus", "inprocess", "reason"),
    [
        ("bogus:1", False, "bus spec 'bogus:1': 'bogus' is neither loopback"),
        ("virtual:x", False, "a virtual bus only joins one process"),
        ("loopback", True, "--inprocess runs on the virtual bus, not loopback"),
    ],
)
def test_a_bad_bus_option_is_refused_before_the_results_folder(
    tmp_path: Path, bus: str, inprocess: bool, reason: str
) -> None:
    """A misspelt --bus is the user's option, not a failed run: no folder with a 'failed'
    summary is left behind (as for --start, --can-log and --animate)."""
    out = tmp_path / "run"
    options = RunOptions(out=out, bus=bus, inprocess=inprocess, progress=False)
    with pytest.raises(HilError, match=reason):
        run_scenario(load_scenario(DEFAULT_SCENARIO), options)
    assert not out.exists()


def test_python_can_configuration_is_honoured(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "from-env")
    bus = open_bus(BusSpec.parse("config"))
    try:
        assert bus.channel_info.endswith("from-env") or "from-env" in str(bus.channel_info)
    finally:
        bus.shutdown()


def test_a_dead_hub_answers_at_once_with_a_hint() -> None:
    import socket

    with socket.socket() as s:  # a free port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(BusOpenError, match="nothing listens on 127.0.0.1:.*hil bus serve"):
        open_bus(BusSpec.parse(f"loopback:{port}"))


def test_a_bus_that_cannot_be_opened_leaves_no_results_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """hil run --bus at a hub that is not there (or a spec that cannot be) is one line before
    the results folder is made: the retry the line suggests (hil run without --bus) then runs there;
    it was refused, the folder holding a failed run's files."""
    import socket

    with socket.socket() as s:  # a free port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    scenario = short_default(tmp_path)
    out = tmp_path / "run"
    for bus in (f"loopback:127.0.0.1:{port}", f"softhil:{port},busy_poll=5"):
        argv = ["run", str(scenario), "--out", str(out), "--no-progress", "--bus", bus]
        assert main(argv) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("hil: error: cannot open CAN bus"), err
        assert not out.exists()
        if bus.startswith("loopback"):
            assert err[0].endswith(" (hil run without --bus serves its own)"), err
    assert main(["run", str(scenario), "--out", str(out), "--no-progress"]) == 0


def test_a_listener_that_never_greets_is_a_timeout_not_a_hang() -> None:
    import socket

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        with pytest.raises(BusOpenError, match="did not greet within 0.2 s"):
            open_bus(BusSpec.parse(f"loopback:{port}"), timeout=0.2)


def test_new_frame_kinds_need_only_the_dbc() -> None:
    protocol = Protocol()
    frame = GenericFrame("ValveCommand", 2, {"open_time": 0.05, "vent": 0, "counter": 3})
    message = protocol.encode(frame)
    assert message.arbitration_id == 0x212
    assert protocol.decode(message) == frame
    assert protocol.cycle_time("ValveCommand2") == 0.01
    assert protocol.cycle_time("EMCY1") is None  # event-driven


def test_version_and_defaults_in_help(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith("hil 0.")
    with pytest.raises(SystemExit):
        main(["bus", "serve", "--help"])
    text = capsys.readouterr().out
    assert "(default: 29536)" in text and "(default: 127.0.0.1)" in text


def _subparsers(parser):  # noqa: ANN001, ANN202 - argparse parsers
    import argparse

    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _subparsers(sub)


@pytest.mark.parametrize(
    ("argv", "command", "leftover"),
    [
        (["scenarios", "foo"], "scenarios", "foo"),
        (["bus", "dump", "--nosuch"], "bus dump", "--nosuch"),
        (["run", "--duration", "1"], "run", "--duration"),  # 1 is taken for NAME
    ],
)
def test_an_unknown_argument_is_shown_with_its_command_usage(
    argv: list[str], command: str, leftover: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """argparse reports leftovers at the top level ('usage: hil [-h] ... COMMAND'), which does
    not say what the command takes; its own usage does."""
    with pytest.raises(SystemExit) as done:
        main(argv)
    err = capsys.readouterr().err
    assert done.value.code == 2
    assert err.startswith(f"usage: hil {command} "), err
    assert f"hil {command}: error: unrecognized arguments: {leftover}" in err


def test_every_help_states_each_default_once() -> None:
    """No '(default: [])' for a repeatable option, and no default both in the text and added
    by the formatter ('(default 0.5) (default: 0.5)' in `hil fmu check --help`)."""
    import re

    from hil.cli import build_parser

    helps = [sub.format_help() for sub in _subparsers(build_parser())]
    assert len(helps) > 15
    for text in helps:
        flat = " ".join(text.split())
        assert "(default: [])" not in flat, flat
        for option in re.split(r" (?=--?[a-z])", flat):
            assert option.count("(default") <= 1, option
    replay = next(h for h in helps if h.startswith("usage: hil replay"))
    assert "(default: 0.0)" in " ".join(replay.split())  # a zero default is a default


def test_direct_in_process_bus_equals_the_virtual_bus_with_a_thread(
    tmp_path: Path, short_run
) -> None:
    """The synchronous in-process pair changes no byte of the run."""
    scenario = short_default(tmp_path)
    direct = short_run  # the default in-process bus
    threaded = run(tmp_path, scenario, "thread", bus="virtual:softhil-test-thread")
    assert direct.summary["controller_process"] == "this thread"
    assert threaded.summary["controller_process"] == "thread"
    for name in ("can.log", "signals.csv"):
        assert (direct.out / name).read_bytes() == (threaded.out / name).read_bytes()


def test_camera_pictures_complete_by_their_header_whatever_the_order() -> None:
    from controllers.config import CameraTiming
    from controllers.node import CameraAssembler
    from rigbus.protocol import CameraFrame, CameraMarker

    assembler = CameraAssembler(3)
    # picture 300 (256 + 44 on the wire) holds markers 0 and 2; marker 2 arrives first, the
    # header last, as on a bus where ids arbitrate
    assembler.add(CameraMarker(2, 0.02, 0.03, 44, 0.01))
    assert not assembler.complete(300)
    assembler.add(CameraMarker(0, 0.0, 0.0, 44, 0.01))
    assert not assembler.complete(300)  # no header yet: it could hold marker 1 too
    assembler.add(CameraFrame(44, 0.01, 0b101, 2))
    assert assembler.complete(300)
    picture = assembler.take(300, 3.01)
    assert picture.exposure_time == pytest.approx(3.0)
    assert picture.seen.tolist() == [True, False, True]
    assert np.isnan(picture.points[1]).all() and picture.points[2].tolist() == [0.02, 0.03]
    assert not assembler.complete(300)
    # which pictures are due by which SYNC: 100 Hz, 6 ms latency, 10 ms period
    timing = CameraTiming(period_ticks=10, latency_ticks=6, control_ticks=10, markers=3)
    assert [timing.frames_due(c) for c in range(4)] == [0, 1, 2, 3]
    slow = CameraTiming(period_ticks=20, latency_ticks=6, control_ticks=10, markers=3)
    assert [slow.frames_due(c) for c in range(5)] == [0, 1, 1, 2, 2]


def test_each_segment_takes_its_own_cylinders_geometry(tmp_path: Path) -> None:
    text = (
        'name = "geometry"\nseed = 1\nduration = 0.1\n[robot]\nsegments = 2\n'
        "[robot.cylinder.2]\nbore = 0.02\nstroke = 0.04\nx_start = 0.015\n"
    )
    rig = build_rig(load_scenario(write(tmp_path, text)))
    try:
        fmus = {p.name: p for p in rig.participants}
        for n, (bore, stroke, x_seal) in ((1, (0.0254, 0.05, 0.025)), (2, (0.02, 0.04, 0.015))):
            segment = fmus[f"segment{n}"].slave  # type: ignore[attr-defined]
            got = tuple(segment.get(name) for name in ("bore", "stroke", "x_seal"))
            assert got == pytest.approx((bore, stroke, x_seal)), n
            assert rig.parameters[f"segment{n}"]["x_seal"] == pytest.approx(x_seal)
    finally:
        rig.close()


def test_log_start_reads_offsets_and_naive_instants_as_utc(tmp_path: Path) -> None:
    from dataclasses import replace

    from hil.scenario import log_start

    scenario = load_scenario()

    def at(text: str) -> float:
        return log_start(replace(scenario, recording=replace(scenario.recording, start=text)))

    assert at("2015-06-01T00:00:00Z") == START
    assert at("2015-06-01T02:00:00+02:00") == START
    assert at("2015-06-01T00:00:00") == START


@pytest.mark.parametrize("name", sorted(p.stem for p in DEFAULT_SCENARIO.parent.glob("*.toml")))
def test_every_file_a_run_writes_is_a_result_file(name: str) -> None:
    # RESULT_FILES is what --overwrite and a user's --can-log are checked against: every plot,
    # figure and animation of every robot kind's built-in scenarios must be in it
    from hil.results import RESULT_FILES

    rig = build_rig(load_scenario(DEFAULT_SCENARIO.parent / f"{name}.toml"))
    try:
        names = [f"{spec.name}.png" for spec in rig.plots] + [f"{n}.png" for n, _ in rig.figures]
        if rig.animation is not None:
            names += [f"{rig.animation[0]}.{fmt}" for fmt in ("gif", "mp4")]
    finally:
        rig.close()
    assert set(names) <= set(RESULT_FILES)
