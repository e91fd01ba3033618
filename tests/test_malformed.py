"""Every bad input a user can give is answered by one line and a non-zero exit, never a
traceback, a hang or silence (issue 7): scenarios, the CLI, controller configurations, DBCs,
CAN log names; and a seeded fuzz of the scenario loader that finds only HilError subclasses."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from controllers.__main__ import main as controller_main
from hil.cli import main as hil_main
from hil.errors import HilError
from hil.run import controller_config
from hil.scenario import DEFAULT_SCENARIO, load_scenario
from rigbus.protocol import FrameError, Protocol

DEFAULT_TEXT = DEFAULT_SCENARIO.read_text()


def one_line(capsys: pytest.CaptureFixture[str], code: int, prefix: str) -> str:
    """The run's stderr is exactly one line starting with `prefix`, and the exit non-zero."""
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code != 0, err
    assert len(lines) == 1 and lines[0].startswith(prefix), err
    assert "Traceback" not in err
    return lines[0]


def edit(*edits: tuple[str, str]) -> str:
    text = DEFAULT_TEXT
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new, 1)
    return text


# (case id, scenario text, the key the one line must name)
SCENARIOS = [
    ("tiny-step", edit(("step = 0.001", "step = 1e-300")), "timing.step"),
    (
        "huge-step",
        edit(("step = 0.001", "step = 0.5"), ("control_period = 0.01", "control_period = 0.5")),
        "timing.step",
    ),  # noqa: E501
    ("huge-duration", edit(("duration = 10.0", "duration = 1e300")), "duration"),
    (
        "too-many-cycles",
        edit(
            ("duration = 10.0", "duration = 86000.0"),
            ("step = 0.001", "step = 0.00001"),
            ("control_period = 0.01", "control_period = 0.00001"),
        ),
        "duration",
    ),  # noqa: E501
    ("int-overflow", edit(("duration = 10.0", "duration = 1" + "0" * 40)), "duration"),
    ("infinite-duration", edit(("duration = 10.0", "duration = inf")), "duration"),
    ("megahertz-sine", edit(("frequency = 0.5", "frequency = 1e6")), "task.sine.frequency"),
    ("nyquist-sine", edit(("frequency = 0.5", "frequency = 50.0")), "task.sine.frequency"),
    ("absurd-kp", edit(("crossover = 1.0", "crossover = 1.0\nkp = 1e9")), "controller.kp"),
    ("absurd-ki", edit(("crossover = 1.0", "crossover = 1.0\nki = 1e12")), "controller.ki"),
    ("negative-kp", edit(("crossover = 1.0", "crossover = 1.0\nkp = -1.0")), "controller.kp"),
    ("fast-crossover", edit(("crossover = 1.0", "crossover = 1000.0")), "controller.crossover"),
    (
        "absurd-pressure",
        edit(("max_pressure = 60000.0", "max_pressure = 1e9")),
        "safety.max_pressure",
    ),  # noqa: E501
    ("camera-noise", edit(("noise = 0.0", "noise = 1.0")), "camera.noise"),
    ("any-host", edit(("bitrate = 1000000", 'bitrate = 1000000\nhost = "0.0.0.0"')), "bus.host"),
    ("above-classical-can", edit(("bitrate = 1000000", "bitrate = 2000000")), "bus.bitrate"),
    (
        "unknown-host",
        edit(("bitrate = 1000000", 'bitrate = 1000000\nhost = "no-such-host.invalid"')),
        "bus.host",
    ),  # noqa: E501
    (
        "channel-space",
        edit(("bitrate = 1000000", 'bitrate = 1000000\nchannel = "my bus"')),
        "bus.channel",
    ),  # noqa: E501
    (
        "channel-angle",
        edit(("bitrate = 1000000", 'bitrate = 1000000\nchannel = "<x>"')),
        "bus.channel",
    ),  # noqa: E501
    ("port-range", edit(("bitrate = 1000000", "bitrate = 1000000\nport = 70000")), "bus.port"),
    ("bad-policy", edit(('policy = "strict"', 'policy = "maybe"')), "controller.policy"),
    (
        "huge-timeout",
        edit(('policy = "strict"', 'policy = "strict"\ntimeout = 1e9')),
        "controller.timeout",
    ),  # noqa: E501
    ("wrong-type", edit(("duration = 10.0", 'duration = "ten"')), "duration"),
    ("negative-seed", edit(("seed = 1", "seed = -1")), "seed"),
    ("bad-name", edit(('name = "default"', 'name = "a/b"')), "name"),
    ("unknown-key", edit(("seed = 1", "seed = 1\ncolour = 3")), "colour"),
    (
        "not-a-multiple",
        edit(("control_period = 0.01", "control_period = 0.0105")),
        "timing.control_period",
    ),  # noqa: E501
    ("zero-camera-rate", edit(("rate = 100.0", "rate = 0.0")), "camera.rate"),
    ("steps-not-increasing", edit(("[2.5, -10.0]", "[0.2, -10.0]")), "task.steps"),
    (
        "can-log-folder",
        edit(("[task]", '[recording]\ncan_log = "../x.log"\n\n[task]')),
        "recording.can_log",
    ),  # noqa: E501
    (
        "bad-start",
        edit(("[task]", '[recording]\nstart = "yesterday"\n\n[task]')),
        "recording.start",
    ),  # noqa: E501
    (
        "start-before-1970",
        edit(("[task]", '[recording]\nstart = "1900-01-01T00:00:00Z"\n\n[task]')),
        "recording.start: '1900-01-01T00:00:00Z' is before 1970-01-01T00:00:00Z",
    ),  # noqa: E501
    ("not-toml", "name = \n[[[", "not valid TOML"),
    ("empty-file", "", "name"),
]


@pytest.mark.parametrize("text,key", [c[1:] for c in SCENARIOS], ids=[c[0] for c in SCENARIOS])
def test_bad_scenario_is_one_line_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, key: str
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    code = hil_main(["run", str(path), "--out", str(tmp_path / "out"), "--no-progress"])
    line = one_line(capsys, code, "hil: error: ")
    assert key in line
    assert not (tmp_path / "out").exists()  # validated before anything was written


@pytest.mark.parametrize(
    ("edits", "said"),
    [
        ((("[task]", "[recording]\nstart = 2016-01-01T00:00:00Z\n\n[task]"),),
         "recording.start: must be a string, got the TOML date-time 2016-01-01T00:00:00Z "
         "(quote it)"),
        ((("latency_compensation = true", "latency_compensation = 1"),),
         "controller.latency_compensation: must be true or false, got 1"),
        ((("duration = 10.0", "duration = true"),), "duration: must be a number, got true"),
        ((("duration = 10.0", "duration = {a = 1}"),), "duration: must be a number, got a table"),
        ((("duration = 10.0", "duration = [1]"),), "duration: must be a number, got an array"),
        ((("duration = 10.0", 'duration = "ten"'),), "duration: must be a number, got 'ten'"),
        ((("duration = 10.0", "duration = 1979-05-27"),),
         "duration: must be a number, got the TOML date 1979-05-27 (quote it)"),
    ],
)  # fmt: skip
def test_a_wrong_value_is_shown_as_toml_writes_it(
    tmp_path: Path, edits: tuple[tuple[str, str], ...], said: str
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(edit(*edits))
    with pytest.raises(HilError) as error:
        load_scenario(path)
    assert str(error.value) == f"{path}: {said}"


def test_binary_scenario_and_folder_and_missing_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    binary = tmp_path / "binary.toml"
    binary.write_bytes(bytes(range(256)))
    for path in (binary, tmp_path, tmp_path / "missing.toml"):
        code = hil_main(["run", str(path), "--out", str(tmp_path / "out"), "--no-progress"])
        one_line(capsys, code, "hil: error: ")


def test_remote_host_needs_the_explicit_key(tmp_path: Path) -> None:
    path = tmp_path / "remote.toml"
    path.write_text(
        edit(("bitrate = 1000000", 'bitrate = 1000000\nhost = "0.0.0.0"\nallow_remote = true'))
    )
    assert load_scenario(path).bus.host == "0.0.0.0"


CLI = [
    ("empty-out", ["run", "--out", ""], "--out"),
    ("blank-out", ["run", "--out", "  "], "--out"),
    ("negative-seed", ["run", "--seed", "-1", "--out", "{tmp}/o"], "--seed"),
    ("bus-space", ["run", "--bus", "loop back", "--out", "{tmp}/o"], "bus spec"),
    (
        "inprocess-loopback",
        ["run", "--inprocess", "--bus", "loopback", "--out", "{tmp}/o"],
        "--inprocess",
    ),  # noqa: E501
    ("bad-start", ["run", "--start", "garbage", "--out", "{tmp}/o"], "--start"),
    ("empty-start", ["run", "--start", "", "--out", "{tmp}/o"], "--start: '' is not an ISO"),
    (
        "start-past-9999",
        ["run", "--start", "9999-12-31T23:59:55Z", "--can-log", "can.blf", "--out", "{tmp}/o"],
        "would end after 9999-12-31T23:59:59Z",
    ),
    ("can-log-suffix", ["run", "--can-log", "x.txt", "--out", "{tmp}/o"], "--can-log"),
    ("can-log-folder", ["run", "--can-log", "../escape.log", "--out", "{tmp}/o"], "--can-log"),
    ("bus-load-bitrate", ["bus", "load", "--bitrate", "0"], "--bitrate"),
    ("bus-load-fast", ["bus", "load", "--bitrate", "100000000000"], "--bitrate: 100000000000 "),
    ("bus-load-log-fast", ["bus", "load", "--log", "x.log", "--bitrate", "1000001"], "at most"),
    (
        "bus-load-live-fast",  # before it listens for --seconds, or finds nothing listening
        ["bus", "load", "--bus", "loopback:127.0.0.1:9", "--bitrate", "2000000", "--seconds", "9"],
        "--bitrate: 2000000 bit/s",
    ),
    ("out-is-a-file", ["run", "--out", "{tmp}/file"], "not a folder"),
]


@pytest.mark.parametrize("argv,word", [c[1:] for c in CLI], ids=[c[0] for c in CLI])
def test_bad_command_line_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], word: str
) -> None:
    (tmp_path / "file").write_text("the user's\n")
    code = hil_main(
        [a.replace("{tmp}", str(tmp_path)) for a in argv] + ["--no-progress"] * (argv[0] == "run")
    )  # noqa: E501
    line = one_line(capsys, code, "hil: error: ")
    assert word in line
    assert (tmp_path / "file").read_text() == "the user's\n"
    assert not (tmp_path / "escape.log").exists()
    assert not (tmp_path / "o").exists()  # refused before the results folder


def good_config() -> dict:
    return json.loads(controller_config(load_scenario()).to_json())


def _set(data: dict, path: str, value: object) -> dict:
    *parents, last = path.split(".")
    node = data
    for p in parents:
        node = node[int(p)] if isinstance(node, list) else node[p]
    if isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value
    return data


CONFIGS = [
    (
        "wrong-type",
        lambda: json.dumps(_set(good_config(), "control_period", "fast")),
        "control_period",
    ),  # noqa: E501
    ("unknown-policy", lambda: json.dumps(_set(good_config(), "policy", "maybe")), "policy"),
    ("unknown-key", lambda: json.dumps({**good_config(), "colour": 1}), "colour"),
    (
        "missing-key",
        lambda: json.dumps({k: v for k, v in good_config().items() if k != "lengths"}),
        "lengths",
    ),  # noqa: E501
    ("absurd-kp", lambda: json.dumps(_set(good_config(), "gains.0.Kp", 1e9)), "Kp"),
    (
        "nan",
        lambda: json.dumps(good_config()).replace('"timeout": 10.0', '"timeout": NaN'),
        "timeout",
    ),  # noqa: E501
    ("too-many-cycles", lambda: json.dumps(_set(good_config(), "cycles", 10**12)), "cycles"),
    (
        "tiny-period",
        lambda: json.dumps(_set(good_config(), "control_period", 1e-300)),
        "control_period",
    ),  # noqa: E501
    ("huge-int", lambda: json.dumps(_set(good_config(), "timeout", 10**400)), "timeout"),
    ("not-json", lambda: "{control_period: fast", "not JSON"),
    ("empty", lambda: "", "empty"),
    ("a-list", lambda: "[1, 2]", "object"),
    ("binary", lambda: b"\xff\xfe\x00".decode("latin-1"), "JSON"),
]


@pytest.mark.parametrize("make,word", [c[1:] for c in CONFIGS], ids=[c[0] for c in CONFIGS])
def test_bad_controller_config_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], make, word: str
) -> None:
    path = tmp_path / "controller.json"
    path.write_text(make())
    code = controller_main(["--config", str(path), "--bus", "virtual:malformed"])
    line = one_line(capsys, code, "controller: error: ")
    assert word in line


def test_controller_config_that_is_a_folder_or_missing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for path in (tmp_path, tmp_path / "missing.json"):
        code = controller_main(["--config", str(path), "--bus", "virtual:malformed"])
        one_line(capsys, code, "controller: error: ")
    code = hil_main(["controller", "--config", str(tmp_path), "--bus", "virtual:malformed"])
    one_line(capsys, code, "controller: error: ")


def test_controller_config_from_a_subprocess_is_one_line(tmp_path: Path) -> None:
    import subprocess
    import sys

    (tmp_path / "c.json").write_text('{"policy": 3}')
    result = subprocess.run(
        [sys.executable, "-m", "controllers", "--config", str(tmp_path / "c.json")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 1
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert result.stderr.startswith("controller: error: ")


@pytest.mark.parametrize(
    "text",
    [
        "",
        "not a dbc at all {",
        "BO_ 0x80 SYNC",
    ],
    ids=["empty", "garbage", "truncated"],
)
def test_unreadable_dbc_is_one_frame_error(tmp_path: Path, text: str) -> None:
    path = tmp_path / "bad.dbc"
    path.write_text(text)
    with pytest.raises(FrameError) as caught:
        Protocol(path)
    assert "\n" not in str(caught.value)


def test_missing_dbc_is_one_frame_error(tmp_path: Path) -> None:
    with pytest.raises(FrameError, match="not a readable DBC"):
        Protocol(tmp_path / "none.dbc")


# ---------------------------------------------------------------------- fuzz

FUZZ_CASES = 200


def _mutations(rng: random.Random, text: str) -> str:
    lines = text.splitlines()
    for _ in range(rng.randint(1, 4)):
        i = rng.randrange(len(lines))
        choice = rng.randrange(7)
        if choice == 0:
            del lines[i]
        elif choice == 1:
            lines.insert(i, lines[rng.randrange(len(lines))])
        elif choice == 2 and "=" in lines[i]:
            key = lines[i].split("=")[0]
            value = rng.choice(
                [
                    '""',
                    "0",
                    "-1",
                    "1e300",
                    "-1e300",
                    "nan",
                    "inf",
                    "true",
                    "[]",
                    "{}",
                    "[[1]]",
                    '"x y"',
                    "99999999999999999999999",
                    "1e-300",
                    "0.0",
                    '"0.0.0.0"',
                    "[1, 2, 3]",
                ]
            )
            lines[i] = f"{key}= {value}"
        elif choice == 3:
            j = rng.randrange(len(lines[i]) + 1)
            lines[i] = lines[i][:j] + rng.choice("=[]{}\"'#.,\\0\t ") + lines[i][j:]
        elif choice == 4:
            lines[i] = lines[i][: rng.randrange(len(lines[i]) + 1)]
        elif choice == 5:
            lines[i], lines[-1] = lines[-1], lines[i]
        else:
            lines.insert(i, rng.choice(["[robot]", "[bus]", "[[connections]]", "[task.sine]"]))
    return "\n".join(lines) + "\n"


def test_fuzzed_scenarios_raise_only_hil_errors(tmp_path: Path) -> None:
    rng = random.Random(7)
    base = DEFAULT_TEXT
    errors = ok = 0
    for case in range(FUZZ_CASES):
        path = tmp_path / f"fuzz{case}.toml"
        if case % 5 == 0:
            path.write_bytes(rng.randbytes(rng.randrange(1, 400)))
        else:
            path.write_text(_mutations(rng, base))
        try:
            load_scenario(path)
            ok += 1
        except HilError as exc:
            assert "\n" not in str(exc), (path.read_text(errors="replace"), exc)
            errors += 1
        except Exception as exc:  # pragma: no cover - the failure this test exists to find
            pytest.fail(f"case {case}: {type(exc).__name__}: {exc}\n{path.read_bytes()!r}")
    assert errors > FUZZ_CASES // 2 and ok > 0


def test_a_corrupt_packaged_dbc_is_one_line_from_the_cli(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    bad = tmp_path / "softhil.dbc"
    bad.write_text("BO_ 0x80 SYNC")
    monkeypatch.setattr(Protocol.__init__, "__defaults__", (bad,))
    code = hil_main(["run", "--out", str(tmp_path / "out"), "--no-progress"])
    line = one_line(capsys, code, "hil: error: ")
    assert "not a readable DBC" in line
