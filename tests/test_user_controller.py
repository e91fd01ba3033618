"""Your own controller against the rig: `hil run --controller COMMAND|external` and
`hil replay --controller COMMAND`.

The rig must take any program that speaks the DBC on the bus: softhil's own controller given
as a command line gives the very bytes of a default run; the example controller
(`examples/piston_sine.py`: python-can, cantools and the DBC, nothing from softhil) drives
all six drives of the planar arm; a controller started by hand on the run's bus (`external`)
gives the very bytes too; its recorded runs replay against it as regression tests.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.cli import main as hil_main
from hil.run import RunOptions, run_scenario
from hil.scenario import load_scenario, resolve_scenario
from rigbus.protocol import DBC_PATH
from tests.test_closed_loop import shortened

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "piston_sine.py"
PYTHON = shlex.quote(sys.executable)
SOFTHIL_AS_COMMAND = (
    f"{PYTHON} -m controllers --config {{config}} --bus {{bus}} --report {{report}}"
)
EXAMPLE_COMMAND = (
    f"{PYTHON} {shlex.quote(str(EXAMPLE))} --config {{config}} --interface {{interface}} "
    "--channel {channel} --host {host} --port {port}"
)


# what `hil run` and `hil batch` are given here beside the run's own options: no progress bar,
# and no plots or reports unless a test looks at them
QUIET = ["--no-progress", "--no-reports"]


def _run(path: Path, out: Path, reports: bool = False, **options: object) -> dict:
    """The summary of a run of `path` into `out` (its plots and reports only with `reports`)."""
    given = RunOptions(out=out, progress=False, reports=reports, **options)
    return run_scenario(load_scenario(path), given).summary


@pytest.fixture(scope="module")
def default_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 1 s default run with softhil's controller started the usual way: (scenario, folder)."""
    tmp = tmp_path_factory.mktemp("default")
    path = shortened(tmp, 1.0)
    _run(path, tmp / "run", reports=True)  # its estimation scores are compared with
    return path, tmp / "run"


def _same_run(a: Path, b: Path) -> None:
    for name in ("can.log", "signals.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_softhil_s_controller_given_as_a_command_gives_the_same_bytes(
    default_run: tuple[Path, Path], tmp_path: Path
) -> None:
    path, reference = default_run
    summary = _run(path, tmp_path / "run", controller=SOFTHIL_AS_COMMAND)
    _same_run(reference, tmp_path / "run")
    assert summary["controller_program"] == SOFTHIL_AS_COMMAND
    assert summary["controller_process"] == "process"
    assert summary["controller"]["cycles"] == 100  # its report, read as softhil's is
    expected = json.loads((reference / "summary.json").read_text())
    assert summary["controller"] == expected["controller"]
    assert expected["controller_program"] == "softhil"


def test_a_controller_started_by_hand_on_the_run_s_bus_gives_the_same_bytes(
    default_run: tuple[Path, Path], tmp_path: Path
) -> None:
    """`hil run --controller external` starts none and says where to connect: the user starts
    softhil's controller by hand from that line, as a user would."""
    path, reference = default_run
    out = tmp_path / "run dir"  # given relative, with a space: the line must still work
    run = subprocess.Popen(
        [sys.executable, "-m", "hil", "run", str(path), "--out", "run dir", *QUIET]
        + ["--controller", "external", "--wait", "60"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    try:
        assert run.stderr is not None
        line = run.stderr.readline()
        assert line.startswith("hil: note: waiting 60 s for a controller to send SYNC(0) on ")
        command = shlex.split(line.rpartition("softhil's: ")[2])
        assert command[:4] == ["hil", "controller", "--config", str(out / "controller.json")]
        controller = subprocess.run(
            [sys.executable, "-m", "hil", *command[1:]], cwd=ROOT, timeout=120, check=False
        )
        assert controller.returncode == 0
        assert run.wait(timeout=120) == 0, run.stderr.read()
    finally:
        run.kill()
        run.wait()
    _same_run(reference, out)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["controller_process"] == summary["controller_program"] == "external"
    assert summary["controller"] == {}  # a program started by hand reports nothing to the run


def test_an_external_controller_that_never_comes_fails_the_run_in_one_line_after_wait(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = shortened(tmp_path, 0.2)
    out = tmp_path / "run"
    argv = ["run", str(path), "--out", str(out), *QUIET, "--controller", "external"]
    assert hil_main([*argv, "--wait", "0.3"]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[0].startswith("hil: note: waiting 0.3 s for a controller")
    assert lines[1:] == [
        "hil: error: no SYNC(0) from the controller within 0.3 s of the start; the plant stopped"
    ]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed" and "no SYNC(0)" in summary["error"]
    assert (out / "controller.json").is_file() and not (out / "controller.log").exists()


def test_an_external_controller_on_another_channel_of_the_hub_is_named(tmp_path: Path) -> None:
    """A controller started by hand on the right hub but the wrong channel (its python-can
    config's `can0`, say) sees an empty bus and the run none of its SYNCs: the error names
    the channel it joined."""
    import can

    path = shortened(tmp_path, 0.2)
    run = subprocess.Popen(
        [sys.executable, "-m", "hil", "run", str(path), "--out", str(tmp_path / "run")]
        + ["--no-progress", "--controller", "external", "--wait", "3"],
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    try:
        assert run.stderr is not None
        line = run.stderr.readline()
        port = int(re.search(r"socketcand 127\.0\.0\.1:(\d+), channel softhil", line)[1])
        bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="can0")
        bus.send(can.Message(arbitration_id=0x080, data=b"\x00", is_extended_id=False))
        assert run.wait(timeout=60) == 1
        bus.shutdown()
        assert run.stderr.read().strip().splitlines() == [
            "hil: error: no SYNC(0) from the controller within 3 s of the start; the plant "
            "stopped; a client joined the hub's channel 'can0', not this run's 'softhil' (the "
            "channel of its bus spec)"
        ]
    finally:
        run.kill()
        run.wait()


def test_a_hand_started_controller_that_leaves_mid_run_is_noticed_by_its_closed_connection(
    tmp_path: Path,
) -> None:
    """The run cannot watch a program it did not start, but it hosts the hub the program
    connected to: when the connection that sent the SYNCs closes before the final one, the
    run fails in one line naming it, not with a silent bus after the controller timeout. Here
    the example controller is given a copy of the run's config with 5 cycles: it sends SYNC
    0..5 and exits cleanly."""
    path = shortened(tmp_path, 1.0, ("crossover = 1.0", "crossover = 1.0\ntimeout = 30.0"))
    out = tmp_path / "run"
    run = subprocess.Popen(
        [sys.executable, "-m", "hil", "run", str(path), "--out", str(out), *QUIET]
        + ["--controller", "external", "--wait", "60"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    try:
        assert run.stderr is not None
        line = run.stderr.readline()
        port = line.partition("(socketcand 127.0.0.1:")[2].partition(",")[0]
        assert port.isdigit(), line
        config = json.loads((out / "controller.json").read_text())
        (tmp_path / "five.json").write_text(json.dumps({**config, "cycles": 5}))
        controller = subprocess.run(
            [
                sys.executable,
                str(EXAMPLE),
                "--config",
                str(tmp_path / "five.json"),
                "--port",
                port,
            ],  # fmt: skip
            timeout=120,
            check=False,
        )
        assert controller.returncode == 0
        assert run.wait(timeout=120) == 1
        error = run.stderr.read().strip().splitlines()
    finally:
        run.kill()
        run.wait()
    assert len(error) == 1 and re.fullmatch(
        r"hil: error: the controller's connection to the run's hub \(127\.0\.0\.1:\d+, which "
        r"sent the SYNCs\) closed; the plant stopped at t = 0\.050 s \(after SYNC 5 of 100\)",
        error[0],
    ), error
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed" and "which sent the SYNCs) closed" in summary["error"]


def test_a_closed_sync_connection_is_taken_for_gone_only_after_the_grace(monkeypatch) -> None:
    """A program's exit is named first (by its code); a connection closed for less than
    CLOSED_GRACE, or replaced by one that sends the SYNCs again, is not the controller gone."""
    from hil import controller_peer as peers

    now = [100.0]
    monkeypatch.setattr(peers.time, "monotonic", lambda: now[0])

    class Hub:
        where: str | None = None

        def sender_gone(self) -> str | None:
            return self.where

    peer = peers.ControllerPeer()
    peer.hub = Hub()  # type: ignore[assignment]
    assert peer.gone() is None
    peer.hub.where = "127.0.0.1:5"
    assert peer.gone() is None  # just closed
    now[0] += peers.CLOSED_GRACE * 0.99
    assert peer.gone() is None
    peer.hub.where = None  # another connection sent a SYNC: the grace starts again
    assert peer.gone() is None
    peer.hub.where = "127.0.0.1:6"
    now[0] += peers.CLOSED_GRACE * 0.99
    assert peer.gone() is None
    now[0] += peers.CLOSED_GRACE
    assert peer.gone() == (
        "the controller's connection to the run's hub (127.0.0.1:6, which sent the SYNCs) closed"
    )
    assert 0.5 <= peers.CLOSED_GRACE <= 2.0


def test_a_started_program_is_given_time_to_show_its_exit_code(monkeypatch) -> None:
    """A program this run started, whose SYNC connection has closed, is waited for up to
    PROCESS_CLOSED_GRACE: its exit code (a signal's, on a loaded host seconds later) names what
    happened, not the closed connection."""
    from hil import controller_peer as peers

    now = [100.0]
    monkeypatch.setattr(peers.time, "monotonic", lambda: now[0])

    class Hub:
        def sender_gone(self) -> str | None:
            return "127.0.0.1:7"

    class Process:
        code: int | None = None

        def poll(self) -> int | None:
            return self.code

    peer = peers.ControllerPeer()
    peer.hub = Hub()  # type: ignore[assignment]
    peer.process = Process()  # type: ignore[assignment]
    assert peer.gone() is None
    now[0] += peers.CLOSED_GRACE * 5  # well past a hand-started controller's grace
    assert peer.gone() is None
    peer.process.code = -15  # type: ignore[attr-defined]
    assert peer.gone() == "the controller exited with code -15"
    peer.process.code = None  # type: ignore[attr-defined]
    now[0] += peers.PROCESS_CLOSED_GRACE
    assert peer.gone() is not None and "closed" in str(peer.gone())


def _ending_after(tmp_path: Path, cycles: int) -> str:
    """The example controller as a command given a copy of the config with `cycles` cycles:
    it sends SYNC 0..cycles and exits with code 0."""
    short = tmp_path / f"cycles-{cycles}.json"
    script = tmp_path / f"cycles-{cycles}.sh"
    script.write_text(
        "#!/bin/sh\n"
        f'{PYTHON} -c "import json, sys; c = json.load(open(sys.argv[1])); '
        f"c['cycles'] = {cycles}; json.dump(c, open(sys.argv[2], 'w'))\" \"$1\" {short} || exit 9\n"
        'shift\nexec "$@"\n'
    )
    script.chmod(0o755)
    return f"{script} {{config}} " + EXAMPLE_COMMAND.replace("{config}", shlex.quote(str(short)))


def test_a_program_that_exits_early_is_told_where_the_run_was(
    default_run: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Exit code 0 before the final SYNC is said to be early; the place is "before SYNC 0"
    for a program that never sent one (not "after SYNC -1"), else the time and the last SYNC
    of all; a replay says the cycle of all the same way."""
    path = shortened(tmp_path, 0.3)
    argv = ["run", str(path), *QUIET, "--controller"]
    early = "hil: error: the controller exited with code 0 before the run's final SYNC; the plant"
    for k, (program, where) in enumerate(
        [
            (f"{PYTHON} -c pass", "stopped before SYNC 0"),
            (_ending_after(tmp_path, 0), "stopped at t = 0.000 s (after SYNC 0 of 30)"),
            (_ending_after(tmp_path, 5), "stopped at t = 0.050 s (after SYNC 5 of 30)"),
        ]
    ):
        out = tmp_path / f"run-{k}"
        assert hil_main([*argv, program, "--out", str(out)]) == 1
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"{early} {where}"
    log = str(default_run[1] / "can.log")
    assert hil_main(["replay", log, "--controller", _ending_after(tmp_path, 5)]) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "hil: error: the controller exited with code 0 before the log's final SYNC; the replay "
        "stopped at cycle 5 of 100"
    )


def test_your_own_python_can_controller_drives_the_six_drives_and_replays(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The example speaks only python-can (socketcand to the run's hub), cantools and the DBC.
    Its commands reach every drive: each setpoint is its sine, to the DBC's 2 um resolution,
    and each piston follows it. Its recorded run replays against it with no divergence, and a
    changed amplitude diverges at the first command. It runs as a copy outside the checkout,
    as a user's would: the DBC comes from the run (SOFTHIL_DBC)."""
    text = resolve_scenario("planar-point-to-point").read_text()
    path = tmp_path / "p.toml"
    path.write_text(text.replace("duration = 40.0", "duration = 0.6"))
    out = tmp_path / "run"
    mine = tmp_path / "mine" / "piston_sine.py"
    mine.parent.mkdir()
    shutil.copy(EXAMPLE, mine)
    command = EXAMPLE_COMMAND.replace(shlex.quote(str(EXAMPLE)), shlex.quote(str(mine)))
    assert command != EXAMPLE_COMMAND
    summary = _run(path, out, controller=command)
    assert summary["status"] == "completed" and summary["frames"]["emcy"] == 0
    assert summary["controller_process"] == "process" and summary["controller"] == {}
    config = json.loads((out / "controller.json").read_text())
    signals = np.genfromtxt(out / "signals.csv", delimiter=",", names=True)
    t = signals["time"]
    for i in range(6):
        low, high = config["x_min"][i], config["x_max"][i]
        # the setpoint latched at SYNC c was computed for t = c T: the sine, from the second SYNC
        sine = (low + high) / 2 + 0.4 * (high - low) / 2 * np.sin(2 * np.pi * t[1:])
        np.testing.assert_allclose(signals[f"x_ref_{i + 1}"][1:], sine, atol=1.01e-6)
        lag = np.abs(signals[f"x_{i + 1}"] - signals[f"x_ref_{i + 1}"])[t > 0.2]
        assert lag.max() < 0.25 * (high - low) / 2, i  # the drive follows it
    log = str(out / "can.log")
    assert hil_main(["replay", log, "--controller", command]) == 0
    assert "61 cycles, 360 controller frames compared, 0 divergence(s)" in capsys.readouterr().out
    changed = command + " --amplitude 0.41"
    assert hil_main(["replay", log, "--controller", changed]) == 1
    shown = capsys.readouterr().out
    assert "first divergence: cycle 0 (t = 0.000 s): DriveCommand1.piston_setpoint" in shown


# the example, sending an id the DBC lacks after its 5th DriveCommand1 (cycle 4) and its 3rd
# (cycle 2) two bytes long: what a replay must report as divergences, not as a traceback
_STRAY_FRAMES = f"""
import runpy, sys
import can

Bus, sent = can.Bus, []

def bus(*args, **kwargs):
    opened = Bus(*args, **kwargs)
    send = opened.send

    def stray(message, timeout=None):
        if message.arbitration_id == 0x201:
            sent.append(message)
            if len(sent) == 3:
                message = can.Message(arbitration_id=0x201, data=bytes(message.data[:2]),
                                      is_extended_id=False)
        send(message, timeout)
        if message.arbitration_id == 0x201 and len(sent) == 5:
            send(can.Message(arbitration_id=0x123, data=b"\\x01", is_extended_id=False), timeout)

    opened.send = stray
    return opened

can.Bus = bus
sys.argv[0] = {str(EXAMPLE)!r}
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def test_a_replay_of_a_program_sending_an_id_the_dbc_lacks_or_a_short_frame_diverges(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], softhil_replay: Any
) -> None:
    """hil replay and softhil_replay name the cycle and the frame (a KeyError or cantools
    DecodeError traceback before): an id the DBC lacks, a DBC message of the wrong length."""
    out = tmp_path / "run"
    _run(shortened(tmp_path, 0.3), out, controller=EXAMPLE_COMMAND)
    program = tmp_path / "stray.py"
    program.write_text(_STRAY_FRAMES)
    stray = EXAMPLE_COMMAND.replace(shlex.quote(str(EXAMPLE)), shlex.quote(str(program)))
    log = str(out / "can.log")
    assert hil_main(["replay", log, "--controller", stray]) == 1
    captured = capsys.readouterr()
    assert captured.err == ""
    assert captured.out.splitlines()[1:] == [
        "  first divergence: cycle 2 (t = 0.020 s): DriveCommand1.(length) expected 4, got 2",
        "  0x123 (not in the DBC).(frame): 1 cycle(s)",
        "  DriveCommand1.(length): 1 cycle(s)",
    ]
    with pytest.raises(AssertionError) as failed:
        softhil_replay(log, controller=stray)
    assert str(failed.value) == (
        f"{log}: 2 divergence(s); first: cycle 2 (t = 0.020 s): DriveCommand1.(length) expected "
        '4, got 2; by signal: {"0x123 (not in the DBC).(frame)": 1, "DriveCommand1.(length)": 1}'
    )


def test_setpoints_outside_the_stroke_are_clamped_and_the_summary_says_so(
    tmp_path: Path,
) -> None:
    """A controller that commands beyond the stroke (in the DBC's range, past the piston's end)
    is not refused: the servo clamps, sets its fault bit 2 in DriveStatus, and the run's summary
    counts the SYNCs after such periods and names the first, with the setpoint."""
    out = tmp_path / "run"
    path = shortened(tmp_path, 0.3)
    summary = _run(path, out, controller=EXAMPLE_COMMAND + " --amplitude 0 --offset 1.6")
    assert summary["status"] == "completed"
    signals = np.genfromtxt(out / "signals.csv", delimiter=",", names=True)
    assert signals["x_ref_1"][2:] == pytest.approx(0.065, abs=1e-6)  # 0.025 + 1.6 * 0.025
    assert int(signals["fault_1"][-1]) & 2  # the servo's clamped bit, as DriveStatus carries it
    # commands latched at SYNC 1 act over 1..2: SYNCs 2..30 follow a clamped period
    assert summary["plant"]["setpoints_clamped"] == 29
    assert summary["plant"]["first_clamped"] == "drive1 at t = 0.020 s, setpoint 0.065 m"
    (warning,) = [w for w in summary["warnings"] if "outside the stroke" in w]
    assert warning.startswith("29 SYNC(s) after a period whose drive setpoint lay outside")
    assert warning.endswith("first: drive1 at t = 0.020 s, setpoint 0.065 m")
    within = _run(path, tmp_path / "within", controller=EXAMPLE_COMMAND + " --offset 0.5")
    assert within["plant"]["setpoints_clamped"] == 0 and within["plant"]["first_clamped"] == ""
    assert not [w for w in within["warnings"] if "outside the stroke" in w]


def test_the_program_gets_the_placeholders_in_its_environment_and_its_report_is_checked(
    default_run: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A user's program sees SOFTHIL_CONFIG, SOFTHIL_BUS, ... (here it starts softhil's
    controller from them); a report it writes is kept, but an entry the summary counts with
    must be a number."""
    path, reference = default_run
    out = tmp_path / "run"
    script = (
        'env | grep ^SOFTHIL_ | sort > "$SOFTHIL_CONFIG.env" && '
        f'{PYTHON} -m controllers --config "$SOFTHIL_CONFIG" --bus "$SOFTHIL_BUS" && '
        """echo '{{"cycles": "many", "intrusions": -1, "overruns": true, """
        """"realtime": true, "mine": 7}}' > "$SOFTHIL_REPORT\""""
    )
    summary = _run(path, out, controller=f"sh -c {shlex.quote(script)}")
    _same_run(reference, out)
    env = dict(line.split("=", 1) for line in (out / "controller.json.env").read_text().split())
    assert env["SOFTHIL_CONFIG"] == str(out / "controller.json")
    assert env["SOFTHIL_REPORT"] == str(out / "controller_report.json")
    assert env["SOFTHIL_BUS"] == summary["bus"]
    assert env["SOFTHIL_INTERFACE"] == "socketcand" and env["SOFTHIL_CHANNEL"] == "softhil"
    assert env["SOFTHIL_HOST"] == "127.0.0.1" and f":{env['SOFTHIL_PORT']}," in summary["bus"]
    assert env["SOFTHIL_REALTIME"] == "0"
    assert env["SOFTHIL_DBC"] == str(DBC_PATH.resolve()) and Path(env["SOFTHIL_DBC"]).is_file()
    assert summary["controller"] == {"mine": 7}
    assert summary["intrusions"] == {"count": 0, "first": None}
    err = capsys.readouterr().err
    assert "cycles = 'many' is not a count or a time" in err
    assert "intrusions = -1 is not a count or a time" in err
    assert "overruns = True is not a count or a time" in err
    assert "realtime without overruns, max_lateness and mean_lateness; left out" in err


def test_a_user_program_that_fails_is_named_with_its_last_words(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = shortened(tmp_path, 0.2)
    out = tmp_path / "run"
    program = f"{PYTHON} -c \"print('no rig for me'); raise SystemExit(3)\""
    argv = ["run", str(path), "--out", str(out), *QUIET, "--controller", program]
    assert hil_main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hil: error: the controller exited with code 3 "
                                               "(no rig for me)")  # fmt: skip
    assert json.loads((out / "summary.json").read_text())["status"] == "failed"
    assert (out / "controller.log").read_text() == "no rig for me\n"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--controller", ""], "--controller: an empty command"),
        (["--controller", "x {nope}"], "--controller: unknown placeholder {nope} in 'x {nope}'"),
        (["--controller", "x {"], "--controller: a stray '{' in 'x {'"),
        (["--controller", "x 'a"], '--controller: cannot split "x \'a": No closing quotation'),
        (["--controller", "/no/such/ctl"], "--controller: cannot start '/no/such/ctl': no such"),
        (["--controller", "no-such-ctl-x"], "cannot start 'no-such-ctl-x': not found on PATH"),
        (["--controller", "{tmp}/plain.txt"], "plain.txt': not an executable file"),
        (["--controller", "plain.txt"], "not found on PATH (the file here is ./plain.txt)"),
        (["--controller", "~/ctl.py"], "no shell runs the command, so ~ and $VARIABLES are not"),
        (["--controller", "$HOME/ctl.py"], "'$HOME/ctl.py': no shell runs the command"),
        (["--controller", "x {config[x]}"], "a stray '{' in 'x {config[x]}'"),
        (["--controller", "x {config!r}"], "a stray '{' in 'x {config!r}'"),
        (["--controller", "x {config.upper}"], "a stray '{'"),
        (["--controller", "x }"], "a stray '}' in 'x }'"),
        (["--controller", "external", "--inprocess"], "--inprocess runs softhil's controller"),
        (["--controller", "true", "--inprocess"], "--controller true runs a program"),
        (["--controller", "external", "--wait", "0"], "--wait: 0 s; give 0 < SECONDS <= 86400"),
        (["--controller", "external", "--wait", "nan"], "--wait: nan s; give 0 < SECONDS"),
    ],
)
def test_a_controller_that_cannot_run_is_one_line_before_the_results_folder(
    argv: list[str],
    message: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    out = tmp_path / "run"
    (tmp_path / "plain.txt").write_text("not a program\n")
    monkeypatch.chdir(tmp_path)
    argv = [arg.replace("{tmp}", str(tmp_path)) for arg in argv]
    assert hil_main(["run", "--out", str(out), *QUIET, *argv]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hil: error: ") and message in err[0], err
    assert not out.exists()


def test_replay_takes_a_command_not_external(
    default_run: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    log = str(default_run[1] / "can.log")
    assert hil_main(["replay", log, "--controller", "external"]) == 1
    assert "--controller external: a replay starts its controller" in capsys.readouterr().err
    assert hil_main(["replay", log, "--controller", "/no/such/ctl"]) == 1
    assert "cannot start '/no/such/ctl': no such file" in capsys.readouterr().err
    assert hil_main(["replay", log, "--controller", SOFTHIL_AS_COMMAND]) == 0
    assert "101 cycles, 200 controller frames compared, 0 divergence(s)" in capsys.readouterr().out


def test_the_example_controller_is_its_own_program() -> None:
    """It must not lean on softhil: a user copies it as the start of their own."""
    source = EXAMPLE.read_text()
    assert "import hil" not in source and "from hil" not in source
    assert "import controllers" not in source and "from controllers" not in source


def test_a_batch_of_your_controller_gives_the_bytes_of_softhil_s_in_process_batch(
    default_run: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`hil batch --controller COMMAND`: each trial runs the program beside it, across
    processes; softhil's controller as that program writes every trial's CAN log and signals
    as the in-process batch does, and batch.json records the command."""
    path = default_run[0]
    base = ["batch", str(path), "--trials", "2", "--workers", "1", *QUIET]
    assert hil_main([*base, "--out", str(tmp_path / "a")]) == 0
    assert hil_main([*base, "--out", str(tmp_path / "b"), "--controller", SOFTHIL_AS_COMMAND]) == 0
    for trial in ("trial-000", "trial-001"):
        _same_run(tmp_path / "a" / trial, tmp_path / "b" / trial)
        summary = json.loads((tmp_path / "b" / trial / "summary.json").read_text())
        assert summary["controller_process"] == "process"
        assert summary["controller_program"] == SOFTHIL_AS_COMMAND
    batch = json.loads((tmp_path / "b" / "batch.json").read_text())
    assert batch["command"].endswith(f"--controller {shlex.quote(SOFTHIL_AS_COMMAND)}")
    assert "--controller" not in json.loads((tmp_path / "a" / "batch.json").read_text())["command"]
    capsys.readouterr()
    assert hil_main([*base, "--out", str(tmp_path / "c"), "--controller", "external"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "hil: error: --controller external: a batch starts its controller; give its command "
        "line instead"
    ]
    assert not (tmp_path / "c").exists()


def test_a_program_that_serves_on_after_the_final_sync_is_stopped_with_a_warning(
    default_run: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A controller that listens until it is stopped (as rig programs do) does not hang the
    run or fail it: it is stopped USER_LINGER s after the final SYNC, and the summary says so.
    (The run waited 30 s, then died of subprocess.TimeoutExpired with a traceback.)"""
    path, reference = default_run
    out = tmp_path / "run"
    program = f"{PYTHON} -m controllers --config {{config}} --bus {{bus}}; exec sleep 600"
    argv = ["run", str(path), "--out", str(out), *QUIET]
    assert hil_main([*argv, "--controller", f"sh -c {shlex.quote(program)}"]) == 0
    warning = (
        "the controller program had not exited 5 s after the final SYNC; the run stopped it "
        "(SIGTERM)"
    )
    assert f"warning: {warning}" in capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["warnings"] == [warning]
    _same_run(reference, out)
    assert not (out / "controller.pid").exists()
    # and it replays: its frames are all in when it lingers (replay waited, then TimeoutExpired)
    replay = ["replay", str(out / "can.log"), "--controller", f"sh -c {shlex.quote(program)}"]
    assert hil_main(replay) == 0
    assert "101 cycles, 200 controller frames compared, 0 divergence(s)" in capsys.readouterr().out


def _gone(pid: int) -> bool:
    """The process has ended (a zombie whose parent has not reaped it counts as ended)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return True
    return "\nState:\tZ" in status


def test_a_program_s_children_end_with_it_in_run_and_replay(
    default_run: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A program is a process group of its own: a shell's background job does not outlive the
    run (it was left running, adopted by init), and the summary says it had to be stopped."""
    path, reference = default_run
    out = tmp_path / "run"
    program = (
        'sleep 300 & echo $! > "$SOFTHIL_CONFIG.job"; '
        f"exec {PYTHON} -m controllers --config {{config}} --bus {{bus}}"
    )
    argv = ["run", str(path), "--out", str(out), *QUIET]
    assert hil_main([*argv, "--controller", f"sh -c {shlex.quote(program)}"]) == 0
    job = int((out / "controller.json.job").read_text())
    assert _gone(job)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["warnings"] == [
        "the controller program left processes running after it exited; the run stopped them"
    ]
    _same_run(reference, out)
    replay = ["replay", str(out / "can.log"), "--controller", f"sh -c {shlex.quote(program)}"]
    assert hil_main(replay) == 0
    assert _gone(int((out / "controller.json.job").read_text()))  # hil replay's own config...
    capsys.readouterr()


def test_a_program_that_ignores_sigterm_is_killed_and_the_warning_says_so(
    default_run: tuple[Path, Path], tmp_path: Path
) -> None:
    path = default_run[0]
    out = tmp_path / "run"
    program = f"trap '' TERM; {PYTHON} -m controllers --config {{config}} --bus {{bus}}; sleep 600"
    argv = ["run", str(path), "--out", str(out), *QUIET]
    assert hil_main([*argv, "--controller", f"sh -c {shlex.quote(program)}"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["warnings"] == [
        "the controller program had not exited 5 s after the final SYNC; the run stopped it "
        "(SIGTERM, then SIGKILL)"
    ]


def test_a_program_may_change_folder_its_paths_are_absolute(
    default_run: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path, reference = default_run
    monkeypatch.chdir(tmp_path)
    program = f"cd / && exec {PYTHON} -m controllers --config {{config}} --bus {{bus}}"
    argv = ["run", str(path), "--out", "run", *QUIET]  # a relative results folder
    monkeypatch.setenv("PYTHONPATH", str(ROOT))  # `cd /` leaves the checkout's packages behind
    assert hil_main([*argv, "--controller", f"sh -c {shlex.quote(program)}"]) == 0
    _same_run(reference, tmp_path / "run")


@pytest.mark.parametrize(
    ("report", "why"),
    [
        ('{"a":' * 600 + "1" + "}" * 600, "nested deeper than 32 levels"),
        ("[" * 100000, "maximum recursion depth exceeded"),
        ('{"x": "' + "y" * (1 << 20) + '"}', f"{(1 << 20) + 9} bytes, more than 1048576"),
    ],
    ids=["deep", "deeper", "big"],
)
def test_a_report_too_deep_or_too_big_is_left_out_and_the_run_completes(
    report: str,
    why: str,
    default_run: tuple[Path, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A user's report goes into summary.json; one nested 600 deep lost the summary to a
    RecursionError, one 100 000 deep failed the run with a traceback."""
    path = default_run[0]
    (tmp_path / "report.json").write_text(report)
    out = tmp_path / "run"
    program = (
        f"{PYTHON} -m controllers --config {{config}} --bus {{bus}} && "
        f"cp {shlex.quote(str(tmp_path / 'report.json'))} {{report}}"
    )
    argv = ["run", str(path), "--out", str(out), *QUIET]
    assert hil_main([*argv, "--controller", f"sh -c {shlex.quote(program)}"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["controller"] == {}
    err = capsys.readouterr().err
    assert "controller_report.json: not a JSON object (" in err and why in err, err


def test_realtime_with_a_program_that_reports_no_pace_is_said_unverified(
    default_run: tuple[Path, Path], tmp_path: Path
) -> None:
    """--realtime with a program: softhil cannot tell whether it kept the pace unless its
    report says; and on a run that was not real-time, a report's lateness is no failure."""
    path = default_run[0]
    program = f"{PYTHON} -m controllers --config {{config}} --bus {{bus}} --realtime"
    summary = _run(path, tmp_path / "rt", controller=program, realtime=True)
    assert summary["realtime"] is True and summary["controller"] == {}
    assert summary["warnings"] == [
        "--realtime: the controller reported no SYNC lateness (report keys realtime, overruns, "
        "max_lateness, mean_lateness), so the real-time pace is not verified"
    ]
    late = (
        '{"realtime": true, "cycles": 100, "overruns": 90, "max_lateness": 1.0, '
        '"mean_lateness": 0.5}'
    )
    program = (
        f"{PYTHON} -m controllers --config {{config}} --bus {{bus}} && "
        f"echo {shlex.quote(late.replace('{', '{{').replace('}', '}}'))} > {{report}}"
    )
    summary = _run(path, tmp_path / "plain", controller=f"sh -c {shlex.quote(program)}")
    assert summary["realtime"] is False and summary["controller"]["overruns"] == 90
    assert summary["status"] == "completed" and summary["warnings"] == []


def test_wait_bounds_a_program_s_start_too(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = shortened(tmp_path, 0.2)
    program = f"sleep 3; exec {PYTHON} -m controllers --config {{config}} --bus {{bus}}"
    argv = ["run", str(path), "--out", str(tmp_path / "run"), *QUIET, "--wait", "0.5"]
    assert hil_main([*argv, "--controller", f"sh -c {shlex.quote(program)}"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "hil: error: no SYNC(0) from the controller within 0.5 s of the start; the plant stopped"
    ]


def test_replay_names_a_program_s_last_words_and_leaks_nothing_when_it_cannot_start(
    default_run: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = str(default_run[1] / "can.log")
    crash = f"{PYTHON} -c \"raise SystemExit('boom in the middle')\""
    assert hil_main(["replay", log, "--controller", crash]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "hil: error: the controller exited with code 1 (boom in the middle); the replay stopped "
        "before SYNC 0"
    ]
    garbage = tmp_path / "garbage"
    garbage.write_bytes(b"\x00\x01\x02 not a program")
    garbage.chmod(0o755)
    assert hil_main(["replay", log, "--controller", str(garbage)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot start" in err[0] and "Exec format error" in err[0], err


def test_last_words_skip_python_can_s_shutdown_warning_and_control_characters(
    tmp_path: Path,
) -> None:
    from hil.program import last_words

    log = tmp_path / "controller.log"
    log.write_text(
        "Traceback ...\nRuntimeError: boom\x1b[2J\n\n"
        "SocketCanDaemonBus was not properly shut down\n"
    )
    assert last_words(log) == "RuntimeError: boom[2J"
    log.write_text("x" * 500 + "\n")
    assert last_words(log) == "x" * 197 + "..."
    assert last_words(tmp_path / "missing.log") == ""


def test_replay_waits_for_a_slow_starting_program_and_wait_bounds_it(
    default_run: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """A program's start (loading a model, say) is bounded by --wait (default 60 s, as in hil
    run), not by the 10 s a replay waits between frames; too short a --wait is one line."""
    from hil.replay import replay

    log = default_run[1] / "can.log"
    program = f"sleep 1.5; exec {PYTHON} -m controllers --config {{config}} --bus {{bus}}"
    slow = f"sh -c {shlex.quote(program)}"
    assert replay(log, controller=slow, timeout=0.5, wait=30.0).ok  # 1.5 s to SYNC(0): waited
    assert hil_main(["replay", str(log), "--controller", slow, "--wait", "0.5"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "hil: error: no SYNC(0) from the controller within 0.5 s of the start; the replay stopped"
    ]


def test_a_program_failing_after_the_final_sync_fails_a_run_that_is_scored_whole(
    default_run: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every cycle was served and recorded: the run writes its metrics and plots as ever, and
    then fails on the program's exit code (it failed without metrics or plots)."""
    path, reference = default_run
    out = tmp_path / "run"
    program = f"{PYTHON} -m controllers --config {{config}} --bus {{bus}}; echo bye; exit 5"
    argv = ["run", str(path), "--out", str(out), "--no-progress"]
    assert hil_main([*argv, "--controller", f"sh -c {shlex.quote(program)}"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    line = "the controller failed with code 5 after the final SYNC (bye)"
    assert err == [f"hil: error: {line}"]
    _same_run(reference, out)
    summary = json.loads((out / "summary.json").read_text())
    expected = json.loads((reference / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["error"] == line
    assert summary["rms_tracking_error"] == expected["rms_tracking_error"]
    assert (out / "curvature.png").is_file()
    for name in ("raw", "kf", "ukf"):  # scored too (its update times are wall-clock)
        assert summary["estimation"][name]["rms"] == expected["estimation"][name]["rms"]
