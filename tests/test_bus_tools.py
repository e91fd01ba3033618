"""Tests of the bus tools (`hil bus dump/record/replay/send/load/up`, hil.bustools).

Logs are made here with the run's own CAN logger (hil.recording.CanLogger) from frames encoded
by rigbus.protocol, so they are softhil logs as `hil run` writes them. Live tests use the
loopback hub on 127.0.0.1 with a free port; waits are receive timeouts, never sleeps.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from hil.bus.loopback import LoopbackHub
from hil.bustools.dump import dump, live_frames
from hil.bustools.frames import FrameFilter, load_database, open_spec
from hil.bustools.load import measure
from hil.bustools.logs import LogError, read_log, write_log
from hil.bustools.record import record, sigterm_interrupts
from hil.bustools.replay import replay_lockstep, replay_timed
from hil.bustools.send import encode_message, parse_cansend
from hil.bustools.vcan import socketcan_available
from hil.cli import build_parser, main
from hil.errors import BusError, HilError
from hil.recording import CanLogger
from rigbus.protocol import (
    CameraMarker,
    ControllerState,
    DriveCommand,
    DriveStatus,
    Heartbeat,
    Protocol,
    Sync,
    frame_bits,
)
from tests.helpers import blocking_sockets_time_out, interruptible

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT = 10.0
CYCLES = 12
DRIVES = 2
PERIOD = 0.01


def softhil_frames(cycles: int = CYCLES) -> list[tuple[can.Message, float, bool]]:
    """(message, simulation time, received by the plant) in the order a run logs them."""
    protocol = Protocol()
    out: list[tuple[can.Message, float, bool]] = []
    for c in range(cycles):
        t = c * PERIOD
        out.append((protocol.encode(Sync(c)), t, True))
        if c % 10 == 0:
            for n in range(1, DRIVES + 1):
                out.append((protocol.encode(Heartbeat(n, 5)), t, False))
        if c > 0:
            for m in range(DRIVES + 1):
                marker = CameraMarker(m, 0.01 * m, 0.06 * m, c - 1, 0.01)
                out.append((protocol.encode(marker), t, False))
        for n in range(1, DRIVES + 1):
            status = DriveStatus(n, 0.025 + 1e-4 * c, 1000.0 * n, -500.0, 0, c)
            out.append((protocol.encode(status), t, False))
        for n in range(1, DRIVES + 1):
            out.append((protocol.encode(DriveCommand(n, 0.03, True, c)), t, True))
            out.append((protocol.encode(ControllerState(n, 1.5, 1.25, c)), t, True))
    return out


@pytest.fixture(scope="module")
def run_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A softhil run log (candump .log, simulation time) with one foreign extended frame."""
    path = tmp_path_factory.mktemp("run") / "can.log"
    logger = CanLogger(path)
    for msg, t, received in softhil_frames():
        logger.log(msg, t, received)
    foreign = can.Message(arbitration_id=0x18FF1234, is_extended_id=True, data=b"\x01\x02")
    logger.log(foreign, CYCLES * PERIOD, True)
    logger.log(can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\xaa"), 0.125, False)
    logger.close()
    return path


@pytest.fixture(autouse=True)
def _guard_blocking_sockets() -> Iterator[None]:
    with blocking_sockets_time_out(TIMEOUT):
        yield


@pytest.fixture
def hub() -> Iterator[LoopbackHub]:
    with LoopbackHub() as h:
        yield h


@pytest.fixture
def spec(hub: LoopbackHub) -> str:
    return f"loopback:127.0.0.1:{hub.port}"


@pytest.fixture
def open_buses(spec: str) -> Iterator[list[can.BusABC]]:
    buses: list[can.BusABC] = []
    yield buses
    for bus in buses:
        bus.shutdown()


def connect(spec: str, buses: list[can.BusABC]) -> can.BusABC:
    bus = open_spec(spec)
    buses.append(bus)
    return bus


def recv_n(bus: can.BusABC, n: int) -> list[can.Message]:
    got = []
    for _ in range(n):
        msg = bus.recv(TIMEOUT)
        assert msg is not None, f"timed out after {len(got)} of {n} frames"
        got.append(msg)
    return got


def key(msg: can.Message) -> tuple[int, bool, bool, bytes]:
    return (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, bytes(msg.data))


def one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hil: error: "), err
    return lines[0]


# ------------------------------------------------------------------------------ log formats

# timestamp resolution of each format as python-can writes it [s]
RESOLUTION = {".log": 1e-6, ".asc": 1e-6, ".blf": 1e-8, ".trc": 1e-6, ".csv": 1e-6, ".mf4": 1e-6}
HAS_DIRECTION = {".log", ".asc", ".blf", ".trc", ".mf4"}


@pytest.mark.parametrize("suffix", sorted(RESOLUTION))
def test_every_format_round_trips_a_recorded_run(
    run_log: Path, tmp_path: Path, suffix: str
) -> None:
    if suffix == ".mf4" and importlib.util.find_spec("asammdf") is None:
        pytest.skip("asammdf is not installed (pip install 'softhil[mf4]')")
    original = read_log(run_log)
    path = tmp_path / f"copy{suffix}"
    assert write_log(path, original) == len(original)
    back = read_log(path)
    assert [key(m) for m in back] == [key(m) for m in original]
    if suffix in HAS_DIRECTION:
        assert [m.is_rx for m in back] == [m.is_rx for m in original]
    assert {m.is_rx for m in original} == {True, False}  # the check above means something
    for got, sent in zip(back, original, strict=True):
        assert got.timestamp == pytest.approx(sent.timestamp, abs=RESOLUTION[suffix])
    if suffix not in (".asc", ".mf4"):  # written again in another folder: the same bytes (an
        # ASC header is dated when written: a live recording's date; hil run dates its own)
        (tmp_path / "other").mkdir()
        write_log(tmp_path / "other" / path.name, original)
        assert (tmp_path / "other" / path.name).read_bytes() == path.read_bytes()


def test_logconvert_output_reads_back_the_same(run_log: Path, tmp_path: Path) -> None:
    converted = tmp_path / "converted.asc"
    done = subprocess.run(
        [sys.executable, "-m", "can.logconvert", str(run_log), str(converted)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    original, back = read_log(run_log), read_log(converted)
    assert [key(m) for m in back] == [key(m) for m in original]
    assert [m.is_rx for m in back] == [m.is_rx for m in original]


def _lines_with_garbage(path: Path, garbage: str, at: int) -> str:
    lines = path.read_text().splitlines()
    return "\n".join([*lines[: at - 1], garbage, *lines[at - 1 :]]) + "\n"


def _bad_logs(run_log: Path, tmp: Path) -> list[tuple[Path, str]]:
    messages = read_log(run_log)
    for suffix in (".asc", ".blf", ".trc", ".csv"):
        write_log(tmp / f"good{suffix}", messages)
    blf = (tmp / "good.blf").read_bytes()
    cases = {
        "garbage.log": (_lines_with_garbage(run_log, "hello world", 4), "line 4"),
        "badid.log": (_lines_with_garbage(run_log, "(0.1) can0 1G3#00 R", 2), "line 2"),
        "long.log": (
            _lines_with_garbage(run_log, "(0.1) can0 123#00112233445566778899 R", 3),
            "line 3",
        ),
        "empty.log": ("", "empty log"),
        "empty.blf": (b"", "empty log"),  # not "unpack requires a buffer of 72 bytes"
        "empty.trc": ("", "empty log"),
        "garbage.asc": (_lines_with_garbage(tmp / "good.asc", "garbage here", 9), "line 9"),
        "garbage.trc": (_lines_with_garbage(tmp / "good.trc", "not a trc line", 25), "line 25"),
        "garbage.csv": (_lines_with_garbage(tmp / "good.csv", "garbage", 5), "line 5"),
        "truncated.blf": (blf[:150], "truncated"),  # cut in the first object's header
        "random.blf": (bytes(range(256)) * 8, "file header"),
        "binary.log": (b"\xff\xfe\x00garbage", "line 1"),
        "unknown.xyz": ("(0.0) can0 080#00 R\n", "unknown log format"),
    }
    out = []
    for name, (content, where) in cases.items():
        path = tmp / name
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
        out.append((path, where))
    return out


def test_malformed_logs_are_one_line_naming_file_and_place(
    run_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for path, where in _bad_logs(run_log, tmp_path):
        with pytest.raises(LogError, match=where):
            read_log(path)
        assert main(["bus", "dump", "--log", str(path)]) == 1
        line = one_error_line(capsys)
        assert str(path) in line and where in line, line
        assert capsys.readouterr().out == ""


@pytest.mark.parametrize(
    ("name", "frame_line", "reason"),
    [
        ("odd.log", "(0.000000) vcan0 181#D43", "data 'D43' has an odd number of hex digits"),
        ("bigid.log", "(0.000000) vcan0 9999999999#00", "CAN id '9999999999' is not 3"),
        ("flags.log", "(0.000000) vcan0 40000123#00", "CAN id 40000123 is above 1FFFFFFF"),
        ("remote.log", "(0.000000) vcan0 123#R12", "R takes one dlc digit 0-8"),
        ("short.asc", " 0.000000 1  181             Rx   d 5 10 27", "dlc 5 but 2 data bytes"),
    ],
)
def test_reader_refuses_frames_python_can_would_silently_change(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, frame_line: str, reason: str
) -> None:
    """python-can reads these as D4 03, id 0x19999999, id 0x123, R1 and a 2-byte frame."""
    if name.endswith(".asc"):
        good = tmp_path / "good.asc"
        write_log(good, [can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\x01")])
        lines = good.read_text().splitlines()
        at = lines.index("End TriggerBlock") + 1
        text = "\n".join([*lines[: at - 1], frame_line, *lines[at - 1 :]]) + "\n"
    else:
        at = 2
        text = f"(0.000000) vcan0 080#00 R\n{frame_line} R\n(0.000001) vcan0 080#01 R\n"
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(LogError) as caught:
        read_log(path)
    assert str(caught.value).startswith(f"{path}: line {at}: malformed")
    assert reason in str(caught.value)
    assert main(["bus", "dump", "--log", str(path)]) == 1
    line = one_error_line(capsys)
    assert f"{path}: line {at}:" in line and reason in line, line


def test_truncated_blf_yields_the_frames_before_the_cut_and_warns_once(
    run_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    original = read_log(run_log)
    good = tmp_path / "good.blf"
    write_log(good, original)
    data = good.read_bytes()
    cut = tmp_path / "cut.blf"
    cut.write_bytes(data[: len(data) // 2])
    never_closed = tmp_path / "never-closed.blf"  # what a killed recorder leaves: header unset
    never_closed.write_bytes(data[:16] + (144).to_bytes(8, "little") + data[24:])
    for path, frames in ((cut, None), (never_closed, len(original))):
        warnings: list[str] = []
        back = read_log(path, warnings.append)
        assert 0 < len(back) == (frames or len(back)) <= len(original)
        assert [key(m) for m in back] == [key(m) for m in original[: len(back)]]
        assert len(warnings) == 1 and str(path) in warnings[0], warnings
        assert "truncated" in warnings[0] and f"read the {len(back)} frames" in warnings[0]
        assert main(["bus", "dump", "--raw", "--log", str(path)]) == 0
        out, err = capsys.readouterr()
        assert len(out.strip().splitlines()) == len(back)
        assert [x for x in err.splitlines() if "warning" in x] == [f"hil: warning: {warnings[0]}"]
        assert "Traceback" not in err
    assert len(read_log(cut, lambda _: None)) < len(original)  # the cut lost frames


def frames(count: int) -> list[can.Message]:
    """`count` classic 8-byte frames, 1 ms apart, on 50 standard ids."""
    return [
        can.Message(
            timestamp=i * 1e-3,
            arbitration_id=0x100 + i % 50,
            is_extended_id=False,
            data=bytes([i * 7 % 256, i % 256, 3, 4, 5, 6, 7, 8]),
        )
        for i in range(count)
    ]


def test_a_binary_log_names_the_record_a_bad_frame_or_object_is(tmp_path: Path) -> None:
    """A frame python-can reads but softhil refuses is an error at its record (from 1); so is a
    corrupt object before the cut of a truncated .blf (the cut tolerates only the end)."""
    sent = frames(50)
    sent[3] = can.Message(arbitration_id=0x800, is_extended_id=False, data=b"\x01")
    path = tmp_path / "bad-id.blf"
    write_log(path, sent)
    with pytest.raises(LogError) as caught:
        read_log(path)
    assert str(caught.value) == f"{path}: record 4: malformed .blf log (CAN id 0x800 out of range)"
    big = tmp_path / "big.blf"
    write_log(big, frames(20000))  # containers of 2730 frames (128 kB uncompressed)
    data = bytearray(big.read_bytes())
    second = data.index(b"LOBJ", data.index(b"LOBJ") + 4)
    data[second : second + 4] = b"XXXX"  # the second container's signature
    corrupt = tmp_path / "corrupt.blf"
    corrupt.write_bytes(bytes(data[: len(data) * 2 // 3]))
    with pytest.raises(LogError, match=r"^\S+corrupt\.blf: record 2731: malformed \.blf log"):
        read_log(corrupt, lambda w: pytest.fail(w))


def test_a_blf_with_bytes_after_its_last_object_warns_without_a_count_it_reached(
    tmp_path: Path,
) -> None:
    """The header's object count is named only when frames are missing from it."""
    path = tmp_path / "tail.blf"
    write_log(path, frames(50))
    size = path.stat().st_size
    path.write_bytes(path.read_bytes() + bytes(4))
    warnings: list[str] = []
    assert len(read_log(path, warnings.append)) == 50
    assert warnings == [
        f"{path}: truncated or never closed (the header says {size} bytes, the file has "
        f"{size + 4}): read the 50 frames before the end; whatever was logged after them is lost"
    ]


@pytest.mark.parametrize("suffix", [".log", ".asc", ".csv"])
def test_a_text_log_without_a_frame_is_empty(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"blank{suffix}"
    path.write_text(
        "\n\n" if suffix != ".csv" else "timestamp,arbitration_id,extended,remote,error,dlc,data\n"
    )
    with pytest.raises(LogError) as caught:
        read_log(path)
    assert str(caught.value) == f"{path}: empty log (no CAN frames)"


@pytest.mark.parametrize("suffix", [".log", ".asc"])
def test_a_text_log_cut_inside_its_last_line_yields_the_lines_before_and_warns(
    run_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], suffix: str
) -> None:
    """What a recorder killed mid-write leaves: the last line without its end, malformed. The
    frames before it are read and one warning names the line; the same line with its line end
    (not a cut) stays an error, and a file whose only frame line is cut is an error."""
    original = read_log(run_log)
    good = tmp_path / f"good{suffix}"
    write_log(good, original[:40])
    lines = good.read_text().splitlines()
    frame_lines = [i for i, x in enumerate(lines) if "#" in x or " d " in x]  # log, asc
    last = frame_lines[29]  # the 30th frame, cut inside its data
    text = "\n".join(lines[:last]) + "\n" + lines[last][: lines[last].rindex(" ") - 1]
    cut = tmp_path / f"cut{suffix}"
    cut.write_text(text)
    warnings: list[str] = []
    back = read_log(cut, warnings.append)
    assert [key(m) for m in back] == [key(m) for m in original[:29]]
    assert warnings == [
        f"{cut}: line {last + 1} cut short (no line end, malformed): read the 29 frames before "
        "it; whatever was logged after them is lost"
    ]
    assert main(["bus", "dump", "--raw", "--log", str(cut)]) == 0
    out, err = capsys.readouterr()
    assert len(out.strip().splitlines()) == 29
    assert [x for x in err.splitlines() if "warning" in x] == [f"hil: warning: {warnings[0]}"]
    ended = tmp_path / f"ended{suffix}"
    ended.write_text(text + "\n")
    with pytest.raises(LogError, match=f"line {last + 1}: malformed"):
        read_log(ended)
    alone = tmp_path / f"alone{suffix}"
    alone.write_text("\n".join(lines[: frame_lines[0]]) + "\n" + lines[frame_lines[0]][:-3])
    with pytest.raises(LogError, match="malformed"):
        read_log(alone, lambda w: pytest.fail(w))


def test_missing_log_and_truncated_mf4(tmp_path: Path, run_log: Path) -> None:
    with pytest.raises(LogError, match="no such log file"):
        read_log(tmp_path / "absent.log")
    if importlib.util.find_spec("asammdf") is None:
        return
    write_log(tmp_path / "good.mf4", read_log(run_log))
    data = (tmp_path / "good.mf4").read_bytes()
    (tmp_path / "bad.mf4").write_bytes(data[: len(data) // 2])
    with pytest.raises(LogError, match="bad.mf4"):
        read_log(tmp_path / "bad.mf4")


def test_failed_write_leaves_no_file(tmp_path: Path, run_log: Path) -> None:
    def broken() -> Iterator[can.Message]:
        yield from read_log(run_log)[:5]
        raise LogError("source broke")

    path = tmp_path / "out.blf"
    with pytest.raises(LogError, match="source broke"):
        write_log(path, broken())
    assert not path.exists()
    path.write_text("keep")
    with pytest.raises(LogError, match="exists"):
        write_log(path, read_log(run_log), overwrite=False)
    assert path.read_text() == "keep"


# ------------------------------------------------------------------------------ dump


def test_dump_decodes_a_run_log_with_units_and_counts_unknown_ids(
    run_log: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bus", "dump", "--log", str(run_log)]) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert len(lines) == len(softhil_frames()) + 2
    assert lines[0] == "(0.000000) can0 080#00 R  SYNC counter=0"
    status = next(x for x in lines if " 182#" in x and "counter=3" in x)
    # a value the DBC names is shown with its name (as cantools decode shows it)
    assert "DriveStatus2 piston_position=0.0253 m p_a=2000 Pa p_b=-500 Pa fault=0 (ok)" in status
    assert status.startswith("(0.030000) can0 182#")
    assert "ControllerState1 kappa_ref=1.5 1/m kappa_est=1.25 1/m counter=0" in captured.out
    assert "18FF1234#0102 R  ?" in captured.out
    assert captured.err.strip() == (
        f"{len(lines)} frames, {len(lines) - 2} decoded, 2 unknown (0x123 x1, 0x18FF1234 x1)"
    )
    assert main(["bus", "dump", "--log", str(run_log), "--raw"]) == 0
    captured = capsys.readouterr()  # nothing is decoded: the count says what the DBC knows
    assert "SYNC" not in captured.out and len(captured.out.splitlines()) == len(lines)
    assert captured.err.strip() == (
        f"{len(lines)} frames, {len(lines) - 2} known to the DBC, 2 unknown (0x123 x1, "
        "0x18FF1234 x1)"
    )


def dumped_ids(capsys: pytest.CaptureFixture[str], run_log: Path, *args: str) -> set[int]:
    assert main(["bus", "dump", "--log", str(run_log), "--raw", *args]) == 0
    out = capsys.readouterr().out
    return {int(line.split()[2].split("#")[0], 16) for line in out.splitlines()}


def test_dump_filters_by_id_range_and_name(
    run_log: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert dumped_ids(capsys, run_log, "--id", "0x181-0x201") == {0x181, 0x182, 0x201}
    assert dumped_ids(capsys, run_log, "--id", "182") == {0x182}
    assert dumped_ids(capsys, run_log, "--id", "0x080,0x702") == {0x080, 0x702}
    assert dumped_ids(capsys, run_log, "--message", "DriveStatus*") == {0x181, 0x182}
    assert dumped_ids(capsys, run_log, "--message", "SYNC", "--id", "0x18FF1234") == {
        0x080,
        0x18FF1234,
    }
    assert dumped_ids(capsys, run_log, "--id", "0x280-0x280") == {0x280}


def test_dump_raw_is_a_candump_log_and_count_limits(
    run_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bus", "dump", "--log", str(run_log), "--raw", "--count", "7"]) == 0
    captured = capsys.readouterr()
    copy = tmp_path / "copy.log"
    copy.write_text(captured.out)
    assert [key(m) for m in read_log(copy)] == [key(m) for m in read_log(run_log)[:7]]
    assert captured.err.startswith("7 frames")
    # a log whose channels are numbers (.blf, .trc): named as python-can's logconvert to .log
    # names them (can0, can1; a bare "0" is no interface name)
    for suffix in (".blf", ".trc"):
        other = tmp_path / f"copy{suffix}"
        write_log(other, read_log(run_log)[:3])
        converted = tmp_path / f"converted{suffix}.log"
        subprocess.run([sys.executable, "-m", "can.logconvert", str(other), str(converted)],
                       check=True, capture_output=True)  # fmt: skip
        assert main(["bus", "dump", "--log", str(other), "--raw"]) == 0
        lines = capsys.readouterr().out.splitlines()
        assert lines == converted.read_text().splitlines(), suffix


@pytest.mark.parametrize(
    "args",
    [
        ["--id", "0xZZ"],
        ["--id", "0x18F-0x180"],
        ["--message", "NoSuchMessage*"],
        ["--count", "0"],
        ["--id", "-5"],
        ["--id", "0x180-"],
    ],
)
def test_dump_bad_arguments_are_one_line(
    run_log: Path, args: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bus", "dump", "--log", str(run_log), *args]) == 1
    line = one_error_line(capsys)
    assert "''" not in line  # the text named is the one given ('-5' was reported as '')


@pytest.mark.parametrize(
    ("argv", "reason"),
    [
        (["dump", "--timeout", "-1"], "--timeout must be at least 0 and at most 86400 s"),
        (["dump", "--timeout", "nan"], "--timeout must be at least 0"),
        (["record", "{tmp}/x.log", "--timeout", "nan"], "--timeout must be at least 0"),
        (["record", "{tmp}/x.log", "--timeout", "-1"], "got -1"),
        (["record", "{tmp}/x.log", "--count", "0"], "--count must be positive, got 0"),
        (["record", "{tmp}/x.log", "--count", "-1"], "--count must be positive, got -1"),
        (["record", "", "--timeout", "1"], ".: is a folder; name the log file"),
        (["record", "{tmp}", "--timeout", "1"], "is a folder; name the log file (e.g. "),
        (["replay", "{log}", "--speed", "1e-300"], "--speed must be at least 1e-06"),
        (["replay", "{log}", "--lockstep", "--direction", "T", "--timeout", "inf"], "got inf"),
        (["replay", "{log}", "--lockstep", "--direction", "T", "--timeout", "0"], "above 0"),
        (["load", "--bus", "loopback", "--seconds", "1e300"], "--seconds must be above 0"),
    ],
)
def test_bus_tool_waits_and_counts_are_checked_before_the_bus_opens(
    run_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], reason: str
) -> None:
    """A negative, NaN or endless wait reached python-can as a traceback (or never ended), and
    `record --count 0` stopped after one frame: each is one line, before any bus is opened
    (none listens on the default hub here)."""
    argv = [a.format(tmp=tmp_path, log=run_log) for a in argv]
    assert main(["bus", *argv]) == 1
    assert reason in one_error_line(capsys)
    assert not (tmp_path / "x.log").exists()


def test_dump_of_a_live_bus(spec: str, open_buses: list[can.BusABC]) -> None:
    listener = connect(spec, open_buses)
    sender = connect(spec, open_buses)
    for msg, _, _ in softhil_frames(2):
        sender.send(msg)
    out = _Lines()
    database = load_database()
    tally = dump(live_frames(listener, TIMEOUT), database, FrameFilter(), False, 5, out)
    assert tally.shown == 5 and tally.decoded == 5
    assert "SYNC counter=0" in out.lines[0]
    assert "Heartbeat1 nmt_state=5" in out.lines[1]


class _Lines:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def write(self, text: str) -> None:
        self.lines.extend(t for t in text.splitlines() if t)

    def flush(self) -> None:
        pass


# ------------------------------------------------------------------------------ send


@pytest.mark.parametrize(
    ("text", "frame_id", "extended", "data", "remote"),
    [
        ("080#05", 0x080, False, b"\x05", False),
        ("7FF#0011223344556677", 0x7FF, False, bytes.fromhex("0011223344556677"), False),
        ("18FF1234#01.02.03", 0x18FF1234, True, b"\x01\x02\x03", False),
        ("1FFFFFFF#", 0x1FFFFFFF, True, b"", False),
        ("123#R", 0x123, False, b"", True),
        ("00000123#R8", 0x123, True, b"", True),
    ],
)
def test_cansend_syntax(
    text: str, frame_id: int, extended: bool, data: bytes, remote: bool
) -> None:
    msg = parse_cansend(text)
    assert (msg.arbitration_id, msg.is_extended_id, bytes(msg.data), msg.is_remote_frame) == (
        frame_id,
        extended,
        data,
        remote,
    )
    if text.endswith("R8"):
        assert msg.dlc == 8


@pytest.mark.parametrize(
    "text",
    [
        "800#00",
        "20000000#00",
        "12#00",
        "1234#00",
        "123#001122334455667788",
        "123#0",
        "123#GG",
        "123##1",
        "123#R9",
        "123",
    ],
)
def test_cansend_rejects_bad_frames(text: str) -> None:
    with pytest.raises(HilError):
        parse_cansend(text)


def test_send_message_strict_range_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["bus", "send", "loopback:127.0.0.1:9", "--message", "DriveCommand1"]
    assert main([*argv, "piston_setpoint=0.2", "enable=1", "counter=3"]) == 1
    line = one_error_line(capsys)
    assert "DriveCommand1.piston_setpoint" in line and "[0, 0.1] m" in line
    assert main([*argv, "piston_setpoint=0.1", "enable=1"]) == 1
    assert "missing counter" in one_error_line(capsys)
    assert main([*argv, "speed=1"]) == 1
    assert "no signal 'speed'" in one_error_line(capsys)
    assert main(["bus", "send", "loopback:127.0.0.1:9", "800#01"]) == 1
    one_error_line(capsys)
    database = load_database()
    msg = encode_message(
        database, "DriveCommand1", ["piston_setpoint=0.05", "enable=1", "counter=255"]
    )
    decoded = Protocol().decode(msg)
    assert (decoded.node, decoded.enable, decoded.counter) == (1, True, 255)
    assert decoded.piston_setpoint == pytest.approx(0.05, abs=2e-6)


def test_send_over_the_hub(spec: str, open_buses: list[can.BusABC]) -> None:
    listener = connect(spec, open_buses)
    assert main(["bus", "send", spec, "18FF1234#01.02"]) == 0
    assert main(["bus", "send", spec, "--message", "SYNC", "counter=7"]) == 0
    first, second = recv_n(listener, 2)
    assert key(first) == (0x18FF1234, True, False, b"\x01\x02")
    assert Protocol().decode(second) == Sync(7)


def test_send_refuses_a_remote_frame_the_hub_cannot_carry(
    spec: str, open_buses: list[can.BusABC], capsys: pytest.CaptureFixture[str]
) -> None:
    listener = connect(spec, open_buses)
    for frame in ("123#R", "123#R3"):
        assert main(["bus", "send", spec, frame]) == 1
        line = one_error_line(capsys)
        assert "0x123" in line and "remote" in line, line
    assert main(["bus", "send", spec, "456#01"]) == 0
    (only,) = recv_n(listener, 1)  # nothing of the remote frames reached the bus before it
    assert key(only) == (0x456, False, False, b"\x01")


# ------------------------------------------------------------------------------ record


def test_record_from_the_hub_in_every_format(
    spec: str, open_buses: list[can.BusABC], tmp_path: Path, run_log: Path
) -> None:
    frames = [m for m, _, _ in softhil_frames(3)]
    for suffix in (".log", ".blf", ".asc"):
        recorder = connect(spec, open_buses)
        sender = connect(spec, open_buses)
        for msg in frames:
            sender.send(msg)
        path = tmp_path / f"rec{suffix}"
        assert record(recorder, path, count=len(frames)) == len(frames)
        assert [key(m) for m in read_log(path)] == [key(m) for m in frames]


def test_record_mf4_without_asammdf_is_one_line_before_recording(
    tmp_path: Path,
    run_log: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "asammdf", None)  # absent, installed or not
    path = tmp_path / "x.mf4"
    # port 9: nothing listens; the format is refused before the bus is opened
    assert main(["bus", "record", str(path), "--bus", "loopback:127.0.0.1:9"]) == 1
    line = one_error_line(capsys)
    assert line == f"hil: error: {path}: writing .mf4 needs asammdf (pip install asammdf)"
    with pytest.raises(LogError, match="needs asammdf"):
        write_log(path, read_log(run_log))
    assert not path.exists()
    existing = tmp_path / "y.mf4"
    existing.write_bytes(b"MDF     ")
    with pytest.raises(LogError, match="reading .mf4 needs asammdf"):
        read_log(existing)


class _InterruptedBus(can.BusABC):
    """A bus that delivers some frames, then Ctrl-C arrives."""

    def __init__(self, frames: list[can.Message]) -> None:
        self.frames = list(frames)
        super().__init__(channel="test")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self.frames:
            raise KeyboardInterrupt
        return self.frames.pop(0), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise NotImplementedError


def test_record_stops_on_ctrl_c_with_a_complete_file(tmp_path: Path) -> None:
    frames = [m for m, _, _ in softhil_frames(4)]
    path = tmp_path / "stopped.blf"
    assert record(_InterruptedBus(frames), path) == len(frames)
    assert [key(m) for m in read_log(path)] == [key(m) for m in frames]


def test_a_recording_whose_disk_fills_keeps_the_frames_before(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A live bus cannot be recorded again: when a write fails (a full disk), the frames before
    it stay in the file and the error says how many (the file used to be removed)."""
    import errno

    from hil.bustools import record as recording

    real = recording.open_writer

    class FullAfterTwo:
        def __init__(self, path: Path) -> None:
            self.writer, self.count = real(path), 0

        def on_message_received(self, msg: can.Message) -> None:
            if self.count == 2:
                raise OSError(errno.ENOSPC, "No space left on device")
            self.count += 1
            self.writer.on_message_received(msg)

        def stop(self) -> None:
            self.writer.stop()

    monkeypatch.setattr(recording, "open_writer", FullAfterTwo)
    frames = [m for m, _, _ in softhil_frames(4)]
    path = tmp_path / "full.log"
    with pytest.raises(LogError) as error:
        record(_InterruptedBus(frames), path)
    assert str(error.value) == (
        f"{path}: cannot write frame 3: No space left on device; the 2 frames before it are kept"
    )
    assert [key(m) for m in read_log(path)] == [key(m) for m in frames[:2]]


def test_a_recording_that_cannot_be_finished_is_kept_as_it_is(tmp_path: Path) -> None:
    """/dev/full takes writes and refuses them at the flush: the error says so and the file
    (here the link) is not removed."""
    path = tmp_path / "rec.log"
    path.symlink_to("/dev/full")
    frames = [m for m, _, _ in softhil_frames(2)]
    with pytest.raises(LogError, match=r"cannot finish writing: .*; what was written is kept"):
        record(_InterruptedBus(frames), path, overwrite=True)
    assert path.is_symlink()


def test_sigterm_becomes_keyboard_interrupt() -> None:
    with pytest.raises(KeyboardInterrupt), sigterm_interrupts():
        os.kill(os.getpid(), signal.SIGTERM)
        # the handler runs in this thread once the signal is seen, which may take a moment
        # when another thread of the process took it (a loaded machine: seen failing once)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            time.sleep(0.001)
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL


def test_a_csv_log_has_no_direction_to_choose_or_show(
    tmp_path: Path, run_log: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """python-can's CSV has no direction column: --direction R or T cannot choose frames from
    it (R used to send every frame, the plant's too), and a dump shows no R/T it does not
    know; the raw lines still read back as a .log."""
    csv = tmp_path / "run.csv"
    write_log(csv, read_log(run_log))
    for direction in ("R", "T"):
        argv = [
            "bus",
            "replay",
            str(csv),
            "--direction",
            direction,
            "--bus",
            "loopback:127.0.0.1:9",
        ]
        assert main(argv) == 1
        assert one_error_line(capsys) == (
            f"hil: error: {csv}: a .csv log has no direction column, so --direction {direction} "
            "cannot choose its frames; use --direction all, or a .log, .asc, .blf or .trc log"
        )
    # --lockstep needs a side: it must not send the user round to --direction all and back
    for direction in ("all", "R"):
        argv = ["bus", "replay", str(csv), "--lockstep", "--direction", direction]
        assert main([*argv, "--bus", "loopback:127.0.0.1:9"]) == 1
        assert one_error_line(capsys) == (
            f"hil: error: {csv}: --lockstep replays one side of the log (--direction R or T), "
            "which a .csv log does not record; replay it timed (--speed), or use a .log, .asc, "
            ".blf or .trc log"
        )
    assert main(["bus", "dump", "--log", str(csv), "--raw", "--count", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and not any(line.endswith((" R", " T")) for line in lines), lines
    copy = tmp_path / "copy.log"
    copy.write_text("\n".join(lines) + "\n")
    assert [key(m) for m in read_log(copy)] == [key(m) for m in read_log(csv)][:2]
    assert main(["bus", "dump", "--log", str(run_log), "--raw", "--count", "1"]) == 0
    assert capsys.readouterr().out.rstrip().endswith((" R", " T"))


def test_record_refuses_to_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "exists.log"
    path.write_text("precious\n")
    assert main(["bus", "record", str(path), "--bus", "loopback:127.0.0.1:9"]) == 1
    assert "--overwrite" in one_error_line(capsys)
    assert path.read_text() == "precious\n"
    assert main(["bus", "record", str(tmp_path / "x.pcap")]) == 1
    assert "unknown log format" in one_error_line(capsys)
    assert not (tmp_path / "x.pcap").exists()


# ------------------------------------------------------------------------------ replay


class _FakeClock:
    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


class _SendOnly(can.BusABC):
    def __init__(self) -> None:
        self.sent: list[can.Message] = []
        super().__init__(channel="test")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False


@pytest.mark.parametrize("speed", [1.0, 2.0, 0.5])
def test_timed_replay_scales_the_log_timing(run_log: Path, speed: float) -> None:
    messages = read_log(run_log)
    bus, clock = _SendOnly(), _FakeClock()
    tally = replay_timed(bus, messages, "R", FrameFilter(), speed, clock, clock.sleep)
    received = [m for m in messages if m.is_rx]
    assert tally.sent == len(received)
    assert [key(m) for m in bus.sent] == [key(m) for m in received]
    assert sum(clock.sleeps) == pytest.approx(
        (received[-1].timestamp - received[0].timestamp) / speed
    )
    assert clock.sleeps[0] == pytest.approx(PERIOD / speed)


def test_replay_direction_and_filters(run_log: Path) -> None:
    messages = read_log(run_log)
    database = load_database()
    bus, clock = _SendOnly(), _FakeClock()
    replay_timed(bus, messages, "T", FrameFilter(), 1.0, clock, clock.sleep)
    assert [key(m) for m in bus.sent] == [key(m) for m in messages if not m.is_rx]
    bus = _SendOnly()
    selection = FrameFilter.parse(["0x201-0x202"], ["SYNC"], database)
    replay_timed(bus, messages, "all", selection, 1e9, clock, clock.sleep)
    assert {m.arbitration_id for m in bus.sent} == {0x080, 0x201, 0x202}
    assert len(bus.sent) == 3 * CYCLES


def test_replay_over_the_hub_in_order(
    spec: str, open_buses: list[can.BusABC], run_log: Path
) -> None:
    listener = connect(spec, open_buses)
    assert main(["bus", "replay", str(run_log), "--bus", spec, "--speed", "1000"]) == 0
    messages = read_log(run_log)
    assert [key(m) for m in recv_n(listener, len(messages))] == [key(m) for m in messages]


def _plant_responder(bus: can.BusABC, cycles: int, events: list[str]) -> None:
    """Echo every SYNC(c) with the DriveStatus(c) of each drive; log what happens."""
    protocol = Protocol()
    for _ in range(cycles * (1 + 2 * DRIVES)):
        msg = bus.recv(TIMEOUT)
        if msg is None:
            events.append("timeout")
            return
        frame = protocol.decode(msg)
        events.append(f"got {type(frame).__name__} {frame.counter}")  # type: ignore[union-attr]
        if isinstance(frame, Sync):
            for n in (2, 1):  # the reverse of the log's order: acks are matched, not ordered
                bus.send(protocol.encode(DriveStatus(n, 0.025, 0.0, 0.0, 0, frame.counter)))
                events.append(f"sent DriveStatus {frame.counter}")


def test_lockstep_replay_waits_for_the_echo_of_each_counter(
    spec: str, open_buses: list[can.BusABC], run_log: Path
) -> None:
    replayer = connect(spec, open_buses)
    responder = connect(spec, open_buses)
    events: list[str] = []
    thread = threading.Thread(target=_plant_responder, args=(responder, CYCLES, events))
    thread.start()
    try:
        tally = replay_lockstep(
            replayer, read_log(run_log), "R", FrameFilter(), load_database(), TIMEOUT
        )
    finally:
        thread.join(TIMEOUT)
    assert tally.acknowledged == CYCLES * DRIVES
    assert tally.cycles == CYCLES
    expected = []
    for c in range(CYCLES):
        expected += [f"got Sync {c}"] + [f"sent DriveStatus {c}"] * DRIVES
        expected += [f"got DriveCommand {c}", f"got ControllerState {c}"] * DRIVES
    assert events == expected


def test_lockstep_replay_of_the_plant_side_waits_for_sync_and_commands(
    spec: str, open_buses: list[can.BusABC], run_log: Path
) -> None:
    replayer = connect(spec, open_buses)
    controller = connect(spec, open_buses)
    protocol = Protocol()
    statuses: list[int] = []

    def run_controller() -> None:
        for c in range(3):
            controller.send(protocol.encode(Sync(c)))
            got = 0
            while got < DRIVES:
                msg = controller.recv(TIMEOUT)
                if msg is None:
                    return
                frame = protocol.decode(msg)
                if isinstance(frame, DriveStatus):
                    statuses.append(frame.counter)
                    got += 1
            for n in range(1, DRIVES + 1):
                controller.send(protocol.encode(DriveCommand(n, 0.03, True, c)))
                controller.send(protocol.encode(ControllerState(n, 1.5, 1.25, c)))

    messages = [m for m in read_log(run_log) if m.arbitration_id != 0x123]
    three_cycles = messages[
        : next(i for i, m in enumerate(messages) if m.arbitration_id == 0x080 and m.data[0] == 3)
    ]
    thread = threading.Thread(target=run_controller)
    thread.start()
    try:
        tally = replay_lockstep(
            replayer, three_cycles, "T", FrameFilter(), load_database(), TIMEOUT
        )
    finally:
        thread.join(TIMEOUT)
    assert statuses == [0, 0, 1, 1, 2, 2]
    assert tally.acknowledged == 3 * (1 + 2 * DRIVES)


def test_lockstep_timeout_and_direction_are_one_line(
    spec: str, run_log: Path, capsys: pytest.CaptureFixture[str], open_buses: list[can.BusABC]
) -> None:
    connect(spec, open_buses)  # a silent receiver
    argv = ["bus", "replay", str(run_log), "--bus", spec, "--lockstep"]
    assert main([*argv, "--direction", "R", "--timeout", "0.2"]) == 1
    line = one_error_line(capsys)
    assert "no DriveStatus1 (0x181) with counter 0 within 0.2 s (SYNC cycle 0" in line
    assert main(argv) == 1
    assert "--direction R" in one_error_line(capsys)
    with pytest.raises(BusError):
        replay_lockstep(_SendOnly(), read_log(run_log), "T", FrameFilter(), load_database(), 0)


# ------------------------------------------------------------------------------ load, vcan


def test_load_from_a_log_per_message(run_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    report = measure(read_log(run_log), load_database(), 500_000)
    span = 0.125  # first frame at 0, the last (0x123) at 0.125 s
    assert report.span == pytest.approx(span)
    rows = {r.frame_id: r for r in report.rows}
    assert rows[0x181].frames == CYCLES and rows[0x181].bits == CYCLES * frame_bits(8)
    assert rows[0x18FF1234].bits == frame_bits(2) + 25
    total = sum(r.bits for r in report.rows)
    assert report.load == pytest.approx(total / span / 500_000)
    assert main(["bus", "load", "--log", str(run_log), "--bitrate", "500000"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"bus load {100 * report.load:.1f} % at 500 kbit/s")
    sync_row = next(x for x in out.splitlines() if x.startswith("SYNC "))
    assert sync_row.split() == [
        "SYNC",
        "0x080",
        str(CYCLES),
        f"{CYCLES / span:.2f}",
        f"{100 * CYCLES * frame_bits(1) / total:.1f}",
    ]


def test_load_bad_inputs(run_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bus", "load", "--log", str(run_log), "--bitrate", "0"]) == 1
    one_error_line(capsys)
    assert main(["bus", "load", "default.toml", "--log", str(run_log)]) == 1
    one_error_line(capsys)
    assert main(["bus", "load"]) == 0  # the scenario's implied load is still there
    assert "bus load" in capsys.readouterr().out


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    (action,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(action.choices)


def test_bus_help_states_each_default_once() -> None:
    bus = _subparsers(build_parser())["bus"]
    checked = 0
    for name, command in _subparsers(bus).items():
        formatter = command._get_formatter()
        for action in command._actions:
            if action.help is None:
                continue
            text = formatter._get_help_string(action) % {"default": action.default}
            assert text.lower().count("default") <= 1, (name, action.dest, text)
            checked += 1
    assert checked > 20


def test_bus_spec_errors_are_one_line_naming_the_option(
    tmp_path: Path, run_log: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for argv in (
        ["dump", "--timeout", "0.1"],
        ["record", str(tmp_path / "x.log"), "--timeout", "0.1"],
        ["replay", str(run_log)],
        ["load", "--seconds", "0.1"],
    ):
        assert main(["bus", *argv, "--bus", ""]) == 1
        assert one_error_line(capsys) == (
            "hil: error: --bus: empty bus spec; give one, e.g. loopback or socketcan:vcan0"
        )
    assert not (tmp_path / "x.log").exists()
    assert main(["bus", "dump", "--bus", "loopback:127.0.0.1:9"]) == 1  # nothing listens
    line = one_error_line(capsys)
    assert line.count("cannot open CAN bus loopback:127.0.0.1:9") == 1, line


def test_bus_up_without_socketcan_is_an_error_line_with_the_hub_hint(
    capsys: pytest.CaptureFixture[str],
) -> None:
    if socketcan_available():
        pytest.skip("this kernel has SocketCAN; `hil bus up` would create an interface")
    for action in ("up", "down"):
        assert main(["bus", action]) == 1  # 2 is the parser's wrong usage (README)
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("hil: error: this kernel has no SocketCAN")
        assert "hil bus serve" in err[0]


def test_a_socketcan_bus_without_socketcan_points_every_tool_to_the_hub(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """The hint fits the tool it is given to: `hil bus dump --bus socketcan:vcan0` is not told
    to leave out --bus so that hil run serves its own bus."""
    if socketcan_available():
        pytest.skip("this kernel has SocketCAN")
    for argv in (["dump", "--timeout", "0.1"], ["record", str(tmp_path / "x.log")]):
        assert main(["bus", *argv, "--bus", "socketcan:vcan0"]) == 1
        line = one_error_line(capsys)
        assert "this kernel has no SocketCAN (AF_CAN)" in line, line
        assert "hil bus serve" in line and "--bus loopback:" in line, line


def test_each_seen_echo_satisfies_one_wait_only() -> None:
    # After 256 cycles the counter repeats: a stale echo must not acknowledge a later cycle.
    protocol = Protocol()
    cycle = [protocol.encode(Sync(0)), protocol.encode(DriveStatus(1, 0.025, 0.0, 0.0, 0, 0))]
    cycle[0].is_rx, cycle[1].is_rx = True, False
    echo = protocol.encode(DriveStatus(1, 0.025, 0.0, 0.0, 0, 0))

    class _EchoOnce(_SendOnly):
        def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
            if len(self.sent) == 1 and not getattr(self, "echoed", False):
                self.echoed = True
                return echo, False
            return None, False

    bus = _EchoOnce()
    database = load_database()
    assert replay_lockstep(bus, cycle, "R", FrameFilter(), database, 1.0).acknowledged == 1
    with pytest.raises(BusError, match="counter 0"):  # one echo, two cycles with counter 0
        replay_lockstep(_EchoOnce(), cycle * 2, "R", FrameFilter(), database, 0.05)


def test_dump_ends_on_ctrl_c_with_the_count_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import hil.bustools.dump
    import hil.bustools.frames

    def two_then_ctrl_c(bus: can.BusABC, idle_timeout: float | None) -> Iterator[can.Message]:
        yield Protocol().encode(Sync(4))
        yield can.Message(arbitration_id=0x555, is_extended_id=False, data=b"\x01")
        raise KeyboardInterrupt

    monkeypatch.setattr(hil.bustools.frames, "open_spec", lambda text: _SendOnly())
    monkeypatch.setattr(hil.bustools.dump, "live_frames", two_then_ctrl_c)
    assert main(["bus", "dump"]) == 0
    captured = capsys.readouterr()
    assert len(captured.out.splitlines()) == 2
    assert captured.err.strip() == "2 frames, 1 decoded, 1 unknown (0x555 x1)"


def test_dump_attached_to_a_run_on_an_external_hub_sees_every_frame(tmp_path: Path) -> None:
    """`hil bus dump` on the hub a run uses decodes every frame of that run, and the run's
    results are the same bytes as without it."""
    import os
    import select
    import signal
    import subprocess
    import sys
    import threading
    import time

    from hil.bus.loopback import LoopbackHub
    from hil.run import RunOptions, run_scenario
    from hil.scenario import DEFAULT_SCENARIO, load_scenario
    from rigbus.canbus import BusSpec, open_bus

    text = DEFAULT_SCENARIO.read_text().replace("duration = 10.0", "duration = 0.5")
    scenario_path = tmp_path / "short.toml"
    scenario_path.write_text(text.replace("sine = { start = 7.0", "sine = { start = 0.5"))
    scenario = load_scenario(scenario_path)
    reference = run_scenario(scenario, RunOptions(out=tmp_path / "alone", progress=False))
    hub = LoopbackHub("127.0.0.1").start()
    try:
        dump = subprocess.Popen(
            [sys.executable, "-m", "hil", "bus", "dump", "--bus", f"loopback:{hub.port}", "--raw"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
            preexec_fn=interruptible,  # it is stopped with SIGINT below
        )
        probe = open_bus(BusSpec.parse(f"loopback:{hub.port}"))
        listening = threading.Event()

        def knock() -> None:  # until the dump shows a probe frame, it may not be listening yet
            while not listening.wait(0.1):
                probe.send(can.Message(arbitration_id=0x7FF, data=b"\x01", is_extended_id=False))

        knocker = threading.Thread(target=knock, daemon=True)
        knocker.start()
        try:
            assert dump.stdout is not None
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                ready, _, _ = select.select([dump.stdout], [], [], 1.0)
                if ready and "7FF#01" in dump.stdout.readline():
                    break
            else:
                raise AssertionError("hil bus dump never showed the probe frame")
        finally:
            listening.set()
            knocker.join()
            probe.shutdown()
        watched = run_scenario(
            scenario,
            RunOptions(
                out=tmp_path / "watched", bus=f"loopback:127.0.0.1:{hub.port}", progress=False
            ),
        )
        dump.send_signal(signal.SIGINT)
        out, _ = dump.communicate(timeout=30)
    finally:
        hub.stop()
    for name in ("can.log", "signals.csv"):
        assert (watched.out / name).read_bytes() == (reference.out / name).read_bytes(), name
    seen = [line for line in out.splitlines() if "#" in line and "7FF#" not in line]
    logged = (watched.out / "can.log").read_text().splitlines()
    assert len(seen) == len(logged)
    key = lambda line: line.split()[2]  # noqa: E731 - ID#DATA
    assert sorted(map(key, seen)) == sorted(map(key, logged))


def test_a_count_of_one_frame_is_singular() -> None:
    from hil.bustools.dump import DumpCount

    assert DumpCount(shown=1, decoded=1).line() == "1 frame, 1 decoded"
    assert DumpCount(shown=0).line() == "0 frames, 0 decoded"
    # a filter that selects nothing says so (an --id 0x800 the log lacks printed "0 frames")
    assert DumpCount(passed=7).line() == "0 frames, 0 decoded; 7 not selected by --id/--message"


def test_dump_of_an_id_the_log_lacks_says_how_many_frames_it_passed_over(
    run_log: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    frames = len(read_log(run_log))
    assert main(["bus", "dump", "--log", str(run_log), "--id", "0x800"]) == 0
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.strip() == f"0 frames, 0 decoded; {frames} not selected by --id/--message"
    assert main(["bus", "dump", "--log", str(run_log), "--message", "SYNC", "--raw"]) == 0
    shown = len(capsys.readouterr().out.splitlines())
    assert 0 < shown < frames
