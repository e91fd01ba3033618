"""CAN-log replay: a recorded run replays with zero divergence against its own controller, in
this process and across processes, in every log format; a changed controller fails and names
the first diverging cycle and signal; bad logs get one line."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import can
import pytest

from hil.cli import main
from hil.errors import ReplayError
from hil.replay import assert_replays, replay
from hil.run import RunOptions, run_scenario
from hil.scenario import DEFAULT_SCENARIO, load_scenario

pytest_plugins = ["pytester"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 1.5 s default run (steps up and down), recorded in-process."""
    folder = tmp_path_factory.mktemp("replay")
    text = DEFAULT_SCENARIO.read_text().replace("duration = 10.0", "duration = 1.5")
    text = text.replace("[0.5, 10.0], [2.5, -10.0]", "[0.2, 10.0], [0.9, -6.0]")
    scenario = folder / "short.toml"
    scenario.write_text(text)
    run_scenario(
        load_scenario(scenario), RunOptions(out=folder / "run", inprocess=True, progress=False)
    )
    return folder / "run" / "can.log"


def test_a_run_replays_exactly_in_process_and_as_a_program(recorded: Path) -> None:
    for process in (False, True):
        result = replay(recorded, process=process)
        assert result.ok, result.divergences[:3]
        assert result.cycles == 151
        assert result.frames_compared == 2 * 150  # command + state per cycle, none after the last


def test_a_changed_gain_fails_and_names_the_first_cycle(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (recorded.parent / "scenario.toml").read_text()
    changed = tmp_path / "changed.toml"
    changed.write_text(text.replace("crossover = 1.0", "crossover = 1.0\nki = 0.02"))
    code = main(
        ["replay", str(recorded), "--scenario", str(changed), "--json", str(tmp_path / "r.json")]
    )
    out = capsys.readouterr().out
    assert code == 1
    result = replay(recorded, load_scenario_config(changed))
    first = result.divergences[0]
    # cycle 0 has no estimate error yet (no picture, zero integral): the integral gain shows
    # from the first cycle with an error on
    assert first.cycle >= 1
    assert (first.message, first.signal) == ("DriveCommand1", "piston_setpoint")
    assert f"first divergence: cycle {first.cycle} (t = {first.time:.3f} s): " in out
    assert first.expected != first.actual
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["status"] == "diverged" and report["first"] == str(first)
    # a tolerance wider than the change lets it pass
    wide = replay(recorded, load_scenario_config(changed), tolerance=0.05)
    assert wide.ok


def load_scenario_config(path: Path):  # noqa: ANN201
    from hil.rig import robot_kind

    scenario = load_scenario(path)
    return robot_kind(scenario.robot.kind).controller_config(scenario)


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".trc"])
def test_a_log_converted_by_python_can_replays_the_same(
    recorded: Path, tmp_path: Path, suffix: str
) -> None:
    converted = recorded.parent / f"converted{suffix}"
    subprocess.run(
        [sys.executable, "-m", "can.logconvert", str(recorded), str(converted)], check=True
    )
    try:
        assert replay(converted).ok
    finally:
        converted.unlink()


def test_the_pytest_fixture_for_users(recorded: Path, pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        f"""
        def test_my_controller(softhil_replay):
            result = softhil_replay({str(recorded)!r})
            assert result.cycles == 151
        """
    )
    pytester.runpytest_inprocess().assert_outcomes(passed=1)


def test_assert_replays_raises_with_the_first_divergence(recorded: Path, tmp_path: Path) -> None:
    text = (recorded.parent / "scenario.toml").read_text()
    changed = tmp_path / "changed.toml"
    changed.write_text(text.replace("crossover = 1.0", "crossover = 1.5"))
    with pytest.raises(AssertionError, match=r"first: cycle \d+ .*DriveCommand1\.piston_setpoint"):
        assert_replays(recorded, load_scenario_config(changed))


def test_bad_options_are_one_line_before_the_replay_runs(
    recorded: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """--json a folder or in a missing folder, and a tolerance for a signal the DBC lacks, are
    refused before any cycle is replayed (no IsADirectoryError after the whole replay)."""
    import hil.replay

    ran: list[bool] = []
    monkeypatch.setattr(hil.replay, "read_cycles", lambda *a: ran.append(True) or [])
    cases = {
        ("--json", str(tmp_path)): f"--json {tmp_path}: is a folder",
        ("--json", str(tmp_path / "no" / "r.json")): f"{tmp_path / 'no'}: no such folder",
        ("--tolerance-for", "nosuch=1"): "tolerance for 'nosuch': no such signal in",
        ("--tolerance-for", "DriveCommand1.nosuch=1"): "'DriveCommand1.nosuch': no such signal",
        ("--tolerance-for", "kappa_est=nan"): "--tolerance-for 'kappa_est=nan': expected SIGNAL=",
        ("--wait", "0"): "--wait: 0 s; give 0 < SECONDS <= 86400 (a day)",
        ("--wait", "nan"): "--wait: nan s; give 0 < SECONDS",
        ("--wait", "1e6"): "--wait: 1e+06 s; give 0 < SECONDS",
    }
    # the recording and the run's results are not for --json to overwrite (it did, silently)
    log_link = tmp_path / "other-name.json"
    log_link.symlink_to(recorded)
    foreign_log = tmp_path / "mine.blf"
    foreign_log.write_bytes(b"LOGG")
    copied = tmp_path / "summary.json"  # a run's file copied without its manifest
    copied.write_text("{}")
    protected = {
        ("--json", str(recorded)): f"--json {recorded}: is the log being replayed",
        ("--json", str(log_link)): f"--json {log_link}: is the log being replayed",
        ("--json", str(recorded.parent / "summary.json")): "a file of the run",
        ("--json", str(recorded.parent / "controller.json")): "a file of the run",
        ("--json", str(foreign_log)): "is a CAN log",
        ("--json", str(copied)): "a file of the run",
        # the run's manifest (replaced, the run's own files were no longer softhil's to overwrite)
        (
            "--json",
            str(recorded.parent / ".softhil-manifest"),
        ): "is softhil's own .softhil-manifest",
    }
    before = {path: Path(path).read_bytes() for (_, path) in protected}
    lock = recorded.parent / ".softhil.lock"  # not there: --json must not make one either
    protected[("--json", str(lock))] = "is softhil's own .softhil.lock of a run"
    for argv, reason in {**cases, **protected}.items():
        assert main(["replay", str(recorded), *argv]) == 1, argv
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and reason in err[0], (argv, err)
    assert not ran
    assert all(Path(path).read_bytes() == data for path, data in before.items())
    assert not lock.exists()
    # the signal and the message's signal are both names a tolerance may use
    assert hil.replay.check_tolerances(hil.replay.Protocol(), {"piston_setpoint": 1}) is None
    hil.replay.check_tolerances(hil.replay.Protocol(), {"DriveCommand1.piston_setpoint": 1})


def _drop(lines: list[str], cycle: int, frame_id: str) -> list[str]:
    """The log's lines without the first `frame_id` frame after SYNC(`cycle`)."""
    sync = next(i for i, x in enumerate(lines) if f" 080#{cycle:02X} R" in x)
    gone = next(i for i in range(sync + 1, len(lines)) if f" {frame_id}#" in lines[i])
    return lines[:gone] + lines[gone + 1 :]


def test_a_log_lacking_a_frame_the_controller_waits_for_is_named_before_the_replay(
    recorded: Path, tmp_path: Path
) -> None:
    """The controller, under its strict policy, would wait its 10 s for the frame and then ask
    whether the plant runs; the replay names the cycle and the frame at once instead, and tells
    a frame missing here from a log of another robot (which never holds the frame)."""
    import dataclasses

    from hil.cycles import read_cycles, read_log
    from hil.replay import check_served
    from rigbus.protocol import Protocol

    lines = recorded.read_text().splitlines()
    config = load_scenario_config(recorded.parent / "scenario.toml")
    cases = {
        ("181", 5): "cycle 5 (t = 0.050 s) lacks DriveStatus1, which softhil's controller "
        "waits for at SYNC 5 under its strict policy: frames missing from the log?",
        ("27F", 7): "cycle 7 (t = 0.070 s) lacks camera frame 6, which",
        ("281", 1): "cycle 1 (t = 0.010 s) lacks camera frame 0, which",  # a marker: none at 0
        ("181", 150): "cycle 150 (t = 1.500 s) lacks DriveStatus1",  # the final SYNC's too
    }
    for (frame_id, cycle), reason in cases.items():
        path = _write(
            tmp_path, f"no-{frame_id}-{cycle}.log", "\n".join(_drop(lines, cycle, frame_id))
        )
        with pytest.raises(ReplayError) as error:
            replay(path, config, timeout=60.0)  # would the controller run, it would wait 60 s
        assert str(error.value).startswith(f"{path}: {reason}"), str(error.value)
    # a stale status (the counter of another cycle) is not the one the controller waits for
    stale = list(lines)
    index = next(i for i, x in enumerate(stale) if " 080#03 R" in x)
    status = next(i for i in range(index, len(stale)) if " 181#" in stale[i])
    stale[status] = stale[status][:-4] + "02 T"  # DriveStatus1's counter (last byte): 2 not 3
    path = _write(tmp_path, "stale.log", "\n".join(stale))
    with pytest.raises(ReplayError, match="cycle 3 .* lacks DriveStatus1"):
        replay(path, config)
    # the arm's six drives against a one-drive log: a log of another robot
    six = dataclasses.replace(
        config,
        lengths=config.lengths * 6,
        x_mid=config.x_mid * 6,
        x_min=config.x_min * 6,
        x_max=config.x_max * 6,
        gains=config.gains * 6,
        bends=config.bends * 6,
        feedforward=config.feedforward * 6,
    )
    with pytest.raises(ReplayError) as error:
        check_served(read_cycles(read_log(recorded), Protocol(), "r"), six, Protocol(), "r")
    assert str(error.value) == (
        "r: cycle 0 (t = 0.000 s) lacks DriveStatus2, DriveStatus3, DriveStatus4, DriveStatus5, "
        "DriveStatus6, which softhil's controller waits for at SYNC 0 under its strict policy: "
        "the log holds no DriveStatus2 at all: the log of another robot than the controller's "
        "(its controller.json or --scenario)?"
    )
    blind = [x for x in lines if not any(f" {i}#" in x for i in ("27F", "280", "281"))]
    path = _write(tmp_path, "no-camera.log", "\n".join(blind))
    with pytest.raises(ReplayError, match=r"cycle 1 .* lacks camera frame 0, .* the log holds "
                       r"no camera frames at all: the log of another robot"):  # fmt: skip
        replay(path, config)
    # under the hold policy the controller goes on past a missing frame, as in a run: replayed
    path = tmp_path / "no-181-5.log"
    held = dataclasses.replace(config, policy="hold", timeout=0.2)
    result = replay(path, held)
    assert result.cycles == 151


def test_a_log_of_a_run_that_stopped_early_says_so(recorded: Path, tmp_path: Path) -> None:
    lines = recorded.read_text().splitlines()
    folder = tmp_path / "stopped"
    folder.mkdir()
    shutil.copy(recorded.parent / "controller.json", folder)
    cut = next(i for i, x in enumerate(lines) if " 080#64 R" in x)  # SYNC 100
    path = _write(folder, "can.log", "\n".join(lines[:cut]))
    summary = {"status": "interrupted", "error": "interrupted (SIGINT)", "can_log": "can.log"}
    (folder / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(ReplayError) as error:
        replay(path)
    assert str(error.value) == (
        f"{path}: 100 SYNC cycles recorded, but the controller runs 151 (the run stopped early: "
        "summary.json beside the log says interrupted (SIGINT))"
    )
    summary.update(status="failed", error="the controller stopped")
    (folder / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(ReplayError, match=r"says failed: the controller stopped\)$"):
        replay(path)
    summary.update(status="completed")  # a completed run's log cut short: not that run's
    (folder / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(ReplayError, match=r"151 \(a log from a different scenario\?\)$"):
        replay(path)
    summary.update(status="failed", can_log="other.log")  # the summary of another log
    (folder / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(ReplayError, match="different scenario"):
        replay(path)


def test_a_csv_log_is_refused_at_once_naming_why(recorded: Path, tmp_path: Path) -> None:
    """python-can's CSV has no direction: replaying one waited for the plant and blamed it."""
    csv = tmp_path / "can.csv"
    with can.Logger(str(csv)) as writer:  # type: ignore[attr-defined]
        for message in can.LogReader(str(recorded)):
            writer.on_message_received(message)
    shutil.copy(recorded.parent / "controller.json", tmp_path / "controller.json")
    with pytest.raises(ReplayError, match=r"can\.csv: a \.csv log cannot be replayed: .* no "):
        replay(csv, timeout=0.5)


def test_a_fish_run_replays_by_its_own_controller_json(tmp_path: Path) -> None:
    """controller.json beside the log is read by its robot kind (it was read as the arm's)."""
    from hil.scenario import resolve_scenario

    text = resolve_scenario("fish-escape").read_text()
    text = re.sub(r"(?m)^duration = .*$", "duration = 0.3", text)
    path = tmp_path / "fish.toml"
    path.write_text(text)
    options = RunOptions(out=tmp_path / "run", inprocess=True, progress=False)
    run_scenario(load_scenario(path), options)
    result = replay(tmp_path / "run" / "can.log")
    assert result.ok and result.cycles == 151, result.divergences[:3]


def test_the_json_summary_is_written_after_the_report(recorded: Path, tmp_path: Path) -> None:
    out = tmp_path / "r.json"
    out.write_text('{"cycles": 0}\n')  # an earlier replay's report: a rerun replaces it
    assert main(["replay", str(recorded), "--json", str(out),
                 "--tolerance-for", "DriveCommand1.piston_setpoint=0.1"]) == 0  # fmt: skip
    summary = json.loads(out.read_text())
    assert summary["cycles"] == 151 and summary["divergences"] == 0, summary
    assert summary["status"] == "passed"
    # a replay that cannot finish replaces the earlier report with its error: a script reading
    # the JSON never takes the last replay's verdict for this one's
    cut = tmp_path / "cut" / "can.log"
    cut.parent.mkdir()
    shutil.copy(recorded.parent / "controller.json", cut.parent)
    cut.write_text("\n".join(recorded.read_text().splitlines()[:100]))
    assert main(["replay", str(cut), "--json", str(out)]) == 1
    summary = json.loads(out.read_text())
    assert summary == {"status": "error", "error": summary["error"]}
    assert summary["error"].startswith(f"{cut}: 15 SYNC cycles recorded"), summary
    changed = tmp_path / "changed.toml"  # a scenario that does not load: the same
    changed.write_text("bogus")
    assert main(["replay", str(recorded), "--json", str(out), "--scenario", str(changed)]) == 1
    assert json.loads(out.read_text())["status"] == "error"
    out.write_text("mine")  # options refused before anything is replayed: nothing written
    assert main(["replay", str(recorded), "--json", str(out), "--tolerance", "-1"]) == 1
    assert out.read_text() == "mine"


def _write(tmp_path: Path, name: str, data: bytes | str) -> Path:
    path = tmp_path / name
    path.write_bytes(data if isinstance(data, bytes) else data.encode())
    return path


def test_bad_logs_get_one_line(recorded: Path, tmp_path: Path) -> None:
    lines = recorded.read_text().splitlines()
    config = load_scenario_config(recorded.parent / "scenario.toml")
    cases = {
        "empty.log": ("", "empty log"),
        "nosync.log": ("\n".join(x for x in lines if " 080#" not in x), "no SYNC frame"),
        "garbage.log": ("(1.0) can0 hello world\n", "line 1"),
        "random.blf": (bytes(range(256)) * 4, "random.blf: "),
        "truncated.blf": (None, ""),  # python-can reads what is whole: too few cycles
        "unknown.log": (lines[0] + "\n(1433116800.0) can0 123#00 T\n", "unknown CAN id 0x123"),
        "jump.log": (
            "\n".join([lines[0], lines[0].replace("080#00", "080#05")]),
            "SYNC counter 5 where 1 was due",
        ),
        "short.log": ("\n".join(lines[: len(lines) // 2]), "a log from a different scenario"),
        "missing.log": (None, "no such log file"),
    }
    blf = tmp_path / "full.blf"
    with can.Logger(str(blf)) as writer:  # type: ignore[attr-defined]
        for message in can.LogReader(str(recorded)):
            writer.on_message_received(message)
    for name, (content, reason) in cases.items():
        if name == "truncated.blf":
            path = _write(tmp_path, name, blf.read_bytes()[: blf.stat().st_size // 2])
        elif content is None:
            path = tmp_path / name
        else:
            path = _write(tmp_path, name, content)
        with pytest.raises(ReplayError) as error:
            replay(path, config)
        assert reason in str(error.value), (name, str(error.value))
        assert "\n" not in str(error.value)
        assert str(error.value).startswith(str(path)) or "different scenario" in str(error.value)


def test_compare_checks_every_signal_of_every_frame() -> None:
    """A difference in a frame's last signal only is found and named."""
    from hil.cycles import Cycle
    from hil.replay import compare
    from rigbus.protocol import ControllerState, DriveCommand, Protocol

    protocol = Protocol()
    recorded = [
        protocol.encode(DriveCommand(1, 0.03, True, 5)),
        protocol.encode(ControllerState(1, 4.0, 3.5, 5)),
    ]
    sent = [
        protocol.encode(DriveCommand(1, 0.03, True, 5)),
        protocol.encode(ControllerState(1, 4.0, 3.25, 5)),  # kappa_est differs, nothing else
    ]
    cycle = Cycle(5, 0.05, (), tuple(recorded))
    result = compare([cycle], [sent], protocol)
    assert [(d.message, d.signal) for d in result.divergences] == [
        ("ControllerState1", "kappa_est")
    ]
    assert result.divergences[0].expected == pytest.approx(3.5)
    assert result.divergences[0].actual == pytest.approx(3.25)
    assert compare([cycle], [recorded], protocol).ok


def test_a_frame_the_dbc_lacks_or_of_the_wrong_length_is_a_divergence_not_a_traceback(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A controller under test that sends an id the DBC does not have, or a DBC message of
    the wrong length, diverges there (a KeyError or cantools DecodeError traceback before)."""
    from hil.cycles import read_cycles, read_log
    from hil.replay import Protocol, compare

    protocol = Protocol()
    cycles = read_cycles(read_log(recorded), protocol, str(recorded))[:3]
    sent = [list(cycle.controller) for cycle in cycles]
    command = next(m for m in sent[1] if m.arbitration_id == 0x201)
    sent[1].append(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
    sent[2] = [m for m in sent[2] if m.arbitration_id != 0x201]
    sent[2].append(can.Message(arbitration_id=0x201, data=bytes(command.data[:2]),
                               is_extended_id=False))  # fmt: skip
    result = compare(cycles, sent, protocol)
    shown = [str(d) for d in result.divergences]
    assert len(shown) == 2, shown
    assert shown[0].endswith("0x123 (not in the DBC).(frame) expected (no frame), got 1")
    assert shown[1].endswith(
        f"DriveCommand1.(length) expected {len(command.data)}, got 2"
    ), shown  # fmt: skip
    assert result.by_signal == {"0x123 (not in the DBC).(frame)": 1, "DriveCommand1.(length)": 1}
    # a frame sent twice in a cycle (the last one counts on the bus) and an extended id that
    # is the number of a DBC message (a different frame on the bus)
    sent = [list(cycle.controller) for cycle in cycles]
    sent[1].append(command)
    sent[2].append(can.Message(arbitration_id=0x201, data=bytes(command.data),
                               is_extended_id=True))  # fmt: skip
    shown = [str(d) for d in compare(cycles, sent, protocol).divergences]
    assert len(shown) == 2, shown
    assert shown[0].endswith("DriveCommand1.(count) expected 1, got 2"), shown
    assert shown[1].endswith(
        "0x00000201 (extended, not in the DBC).(frame) expected (no frame), got 1"
    )
