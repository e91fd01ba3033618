"""The fault matrix (issue 7): every fault ends with the documented exit code, one line,
summary.json stating the reason (when it can be written), and logs that python-can and
cantools read up to their last record. Results folders never lose a user's file.

Runs are short and in-process where the case allows; the cases that need processes (signals to
`hil run`, a killed controller, a killed hub) wait for progress by polling the run's files, never
by sleeping a fixed time."""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import errno
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import cantools.logreader
import pytest

import hil.results
from controllers.node import ControllerNode, RealtimeClock
from hil.blocks import read_blocks
from hil.cli import main as hil_main
from hil.errors import HilError
from hil.run import controller_config
from hil.scenario import DEFAULT_SCENARIO, load_scenario
from hil.summary import realtime_failure
from rigbus.protocol import DriveCommand, Protocol, Sync
from tests.helpers import interruptible

DEFAULT_TEXT = DEFAULT_SCENARIO.read_text()
REPO = Path(__file__).resolve().parents[1]


def scenario_file(tmp_path: Path, duration: float, *edits: tuple[str, str]) -> Path:
    text = DEFAULT_TEXT.replace("duration = 10.0", f"duration = {duration}").replace(
        "sine = { start = 7.0", f"sine = {{ start = {duration}"
    )
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new, 1)
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path


HOLD = ('policy = "strict"', 'policy = "hold"')
# [s] simulated, for the runs a test stops midway (a signal, a killed or frozen controller, a
# killed hub): long enough that a run at 20-40x real time is still going when the test acts
# after its first recorded block (written every 0.25 s); stopped, it costs no more than a short one
LONG = 100.0


def readable(out: Path, can_log: str = "can.log") -> int:
    """Every log in `out` reads to its last record; returns the CAN log's record count."""
    log = out / can_log
    lines = log.read_text().splitlines() if log.exists() else []
    assert all(line.endswith((" R", " T")) for line in lines)
    if lines:
        assert len(list(can.LogReader(str(log)))) == len(lines)
        parser = cantools.logreader.Parser()
        assert all(parser.parse(line) is not None for line in lines)
    signals = out / "signals.csv"
    if signals.exists():
        rows = list(csv.reader(signals.open()))
        assert rows and all(len(r) == len(rows[0]) for r in rows)
        assert signals.read_bytes().endswith(b"\n")
    return len(lines)


def summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def run_cli(
    capsys: pytest.CaptureFixture[str], *argv: str, reports: bool = False
) -> tuple[int, list[str]]:
    """`hil run ARGV` (without the plots and reports unless `reports`): its code and the lines
    of stderr but warnings."""
    code = hil_main(["run", *argv, "--no-progress", *([] if reports else ["--no-reports"])])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, [line for line in err.splitlines() if not line.startswith("  warning")]


# ------------------------------------------------------------------ results folders


def test_out_never_touches_foreign_files(tmp_path: Path, capsys) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    scenario = scenario_file(out, 0.2)  # the user's scenario.toml-like file lives there
    (out / "scenario.toml").write_text("# the user's own scenario\n")
    (out / "summary.json").write_text('{"mine": true}\n')
    (out / "notes.txt").write_bytes(b"\x00\x01 private")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    for extra in ([], ["--overwrite"]):
        code, lines = run_cli(capsys, str(scenario), "--inprocess", "--out", str(out), *extra)
        assert code == 1 and len(lines) == 1
        assert "not empty" in lines[0] or "not written by softhil" in lines[0]
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert not (out / hil.results.LOCK).exists()


@pytest.mark.parametrize(
    "name",
    [
        "signals.csv",
        "signals.units.csv",
        "controller.log",
        "signals.mf4",
        "SIGNALS.csv",
        "logs/can.log",
        "../can.log",
    ],
)
def test_a_can_log_named_as_a_result_file_is_refused_before_the_run(
    tmp_path: Path, capsys, name: str
) -> None:
    # the CAN log would replace the signals (or the controller's log) the run writes: refused,
    # on the command line and in the scenario, in one line, before anything is written
    out = tmp_path / "out"
    scenario = scenario_file(tmp_path, 0.2)
    code, lines = run_cli(
        capsys, str(scenario), "--inprocess", "--out", str(out), "--can-log", name
    )
    assert code == 1 and len(lines) == 1
    assert lines[0].startswith("hil: error: --can-log: ") and repr(name) in lines[0]
    assert not out.exists()
    keyed = scenario_file(tmp_path, 0.2, ("[robot]", f'[recording]\ncan_log = "{name}"\n\n[robot]'))
    code, lines = run_cli(capsys, str(keyed), "--inprocess", "--out", str(out))
    assert code == 1 and len(lines) == 1
    assert ": recording.can_log: " in lines[0] and repr(name) in lines[0]
    assert not out.exists()


def test_rerun_into_its_own_folder_keeps_the_input_scenario(tmp_path: Path, capsys) -> None:
    out = tmp_path / "run"
    assert (
        run_cli(capsys, str(scenario_file(tmp_path, 0.2)), "--inprocess", "--out", str(out))[0] == 0
    )  # noqa: E501
    recorded = out / "scenario.toml"
    text = recorded.read_bytes()
    (out / "my-notes.md").write_text("keep me\n")
    code, lines = run_cli(capsys, str(recorded), "--inprocess", "--out", str(out))
    assert code == 1 and "not empty" in lines[0]
    code, lines = run_cli(capsys, str(recorded), "--inprocess", "--out", str(out), "--overwrite")
    assert code == 0 and not lines  # the same scenario as the file: nothing to say
    assert recorded.read_bytes() == text
    assert (out / "my-notes.md").read_text() == "keep me\n"
    assert summary(out)["status"] == "completed"
    # another seed than the kept file's: the file stays, and the run says where its seed is
    code, lines = run_cli(
        capsys, str(recorded), "--inprocess", "--out", str(out), "--overwrite", "--seed", "7"
    )
    assert code == 0 and recorded.read_bytes() == text and summary(out)["seed"] == 7
    assert lines == [
        f"hil: note: {recorded} is this run's input and is kept as it is; the run used seed 7 "
        "(summary.json)"
    ]


def test_overwrite_replaces_the_signal_blocks_and_refuses_a_foreign_file_among_them(
    tmp_path: Path, capsys
) -> None:
    """--overwrite removes an earlier run's blocks (a longer run's, more of them: none stays
    to be read with the new run's); a file softhil did not write among them refuses the
    rerun before anything is removed."""
    out = tmp_path / "run"
    assert (
        run_cli(capsys, str(scenario_file(tmp_path, 0.3)), "--inprocess", "--out", str(out))[0] == 0
    )  # noqa: E501
    blocks = out / "signals.parquet"
    (blocks / "part-000000.parquet").rename(blocks / "part-000007.parquet")  # as a long run's
    short = scenario_file(tmp_path, 0.1)
    assert run_cli(capsys, str(short), "--inprocess", "--out", str(out), "--overwrite")[0] == 0
    assert [p.name for p in blocks.iterdir()] == ["part-000000.parquet"]
    text = (out / "signals.csv").read_bytes()
    assert text.count(b"\n") == 12  # the header and SYNC 0..10
    (blocks / "mine.txt").write_text("keep me\n")
    before = sorted(p.name for p in out.iterdir())
    code, lines = run_cli(capsys, str(short), "--inprocess", "--out", str(out), "--overwrite")
    assert code == 1 and lines == [
        f"hil: error: results folder {out}: signals.parquet/mine.txt was not written by "
        "softhil; --overwrite replaces only softhil's own files"
    ]
    assert sorted(p.name for p in out.iterdir()) == before
    assert (out / "signals.csv").read_bytes() == text and (blocks / "mine.txt").exists()


def test_second_run_into_a_locked_folder_is_refused_and_a_stale_lock_taken_over(
    tmp_path: Path, capsys
) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / hil.results.LOCK).write_text(f"{os.getppid()}\n")  # a live process holds it
    code, lines = run_cli(
        capsys, str(scenario_file(tmp_path, 0.2)), "--inprocess", "--out", str(out)
    )  # noqa: E501
    assert code == 1 and len(lines) == 1 and "in use by another run" in lines[0]
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (out / hil.results.LOCK).write_text(f"{dead.pid}\n")
    code, lines = run_cli(
        capsys, str(scenario_file(tmp_path, 0.2)), "--inprocess", "--out", str(out)
    )  # noqa: E501
    assert code == 0 and any("stale lock" in line for line in lines)
    assert not (out / hil.results.LOCK).exists()


# ------------------------------------------------------------------ disk full


@contextlib.contextmanager
def disk_full(monkeypatch: pytest.MonkeyPatch, budget: int, only: str = "") -> Iterator[None]:
    """Every results write fails with ENOSPC once `budget` bytes are written (to files whose
    name contains `only`)."""
    left = [budget]
    real = hil.results.write_bytes

    def write(fd: int, data: bytes) -> int:
        name = os.readlink(f"/proc/self/fd/{fd}")
        if only in name and len(data) > left[0]:
            if left[0] == 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            data = data[: left[0]]  # a short write, as a filling disk gives; ENOSPC next
        if only in name:
            left[0] -= len(data)
        return real(fd, data)

    monkeypatch.setattr(hil.results, "write_bytes", write)
    yield


@pytest.mark.parametrize(
    "budget,only,where",
    [
        (0, "", "nothing"),
        (0, "controller.json", "start"),
        (10_000, "can.log", "mid-run"),
        (0, ".png", "end"),
    ],
    ids=["nothing-writable", "start", "mid-run", "end"],
)
def test_disk_full(tmp_path: Path, capsys, monkeypatch, budget: int, only: str, where: str) -> None:
    out = tmp_path / "run"
    with disk_full(monkeypatch, budget, only):
        code, lines = run_cli(
            capsys, str(scenario_file(tmp_path, 1.0)), "--inprocess", "--out", str(out),
            reports=True,  # the plots are the last files a run writes
        )  # fmt: skip
    assert code == 1 and len(lines) == 1, lines
    assert "No space left on device" in lines[0]
    assert not [p for p in out.iterdir() if p.stat().st_size == 0 and p.name != "controller.log"]
    records = readable(out)
    if where == "nothing":
        assert not (out / "summary.json").exists()  # nothing could be written at all
        return
    s = summary(out)
    if where == "start":
        assert "controller.json" in lines[0] and not (out / "controller.json").exists()
        assert s["status"] == "failed" and "controller.json" in s["error"]
        return
    assert s["status"] == "failed" and "No space left on device" in s["error"]
    if where == "mid-run":
        assert records > 0 and (out / "can.log").stat().st_size <= 10_000
    else:
        assert s["rms_tracking_error"] is not None  # the run itself was complete


# ------------------------------------------------------------------ intruders


class Intruder:
    """A second node on the bus that sends a DriveCommand in the controller's name for every
    SYNC it sees (correct counter, a far setpoint)."""

    def __init__(self, bus: can.BusABC, make: Callable[[int], can.Message]) -> None:
        self.bus, self.make, self.sent = bus, make, 0
        self.stop = threading.Event()
        self.protocol = Protocol()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            message = self.bus.recv(timeout=0.05)
            if message is not None and message.arbitration_id == 0x080:
                counter = message.data[0]
                with contextlib.suppress(can.CanError, OSError):
                    self.bus.send(self.make(counter))
                    self.sent += 1

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        self.bus.shutdown()


def foreign_command(counter: int) -> can.Message:
    return Protocol().encode(DriveCommand(1, 0.045, True, counter))


@pytest.mark.parametrize("policy", ["hold", "strict"])
def test_injected_commands_on_the_virtual_bus(tmp_path: Path, capsys, policy: str) -> None:
    channel = f"intruded-{policy}"
    intruder = Intruder(can.Bus(interface="virtual", channel=channel), foreign_command)
    edits = [HOLD] if policy == "hold" else []
    try:
        code, lines = run_cli(
            capsys, str(scenario_file(tmp_path, 1.0, *edits)), "--inprocess", "--bus",
            f"virtual:{channel}", "--out", str(tmp_path / "run"),
        )  # fmt: skip
    finally:
        intruder.close()
    s = summary(tmp_path / "run")
    readable(tmp_path / "run")
    if policy == "hold":
        assert code == 0
        assert s["intrusions"]["count"] > 0 and s["intrusions"]["first"]
        # both ends saw it: the plant a second command per cycle, the controller its own id
        assert s["plant"]["intrusions"] > 0 and s["controller"]["intrusions"] > 0
        assert any("intrusion" in w for w in s["warnings"])
    else:
        assert code == 1 and len(lines) == 1 and "intrusion" in lines[0]
        assert s["status"] == "failed" and "intrusion" in s["error"]


def test_duplicated_frames_are_counted(tmp_path: Path, capsys) -> None:
    """A node that repeats every command and SYNC it hears (a duplicating gateway)."""
    channel = "duplicated"
    bus = can.Bus(interface="virtual", channel=channel)
    stop = threading.Event()

    def echo() -> None:
        while not stop.is_set():
            message = bus.recv(timeout=0.05)
            if message is not None and message.arbitration_id in (0x080, 0x201):
                with contextlib.suppress(can.CanError):
                    bus.send(message)

    thread = threading.Thread(target=echo, daemon=True)
    thread.start()
    try:
        code, _ = run_cli(
            capsys, str(scenario_file(tmp_path, 0.5, HOLD)), "--inprocess", "--bus",
            f"virtual:{channel}", "--out", str(tmp_path / "run"),
        )  # fmt: skip
    finally:
        stop.set()
        thread.join(timeout=5)
        bus.shutdown()
    assert code == 0
    assert summary(tmp_path / "run")["intrusions"]["count"] > 0
    readable(tmp_path / "run")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_for(condition: Callable[[], bool], what: str, limit: float = 60.0) -> None:
    """Poll `condition` (a run's files) until true; a generous limit only against hangs."""
    deadline = time.monotonic() + limit
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def rows(path: Path) -> int:
    try:
        return path.read_bytes().count(b"\n")
    except OSError:
        return 0


def recorded(out: Path) -> bool:
    """Whether a run's blocks of signals (written every 0.25 s of wall time; the CSV is written
    from them when the run ends) hold more than two rows."""
    try:
        return sum(data.shape[1] for _, data, _ in read_blocks(out / "signals.parquet")) > 2
    except HilError:  # a block renamed into place as the folder was listed
        return False


def hil_process(*argv: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "hil", *argv],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=interruptible,
    )


def hil_run_process(scenario: Path, out: Path, *more: str) -> subprocess.Popen[str]:
    """`hil run SCENARIO --out OUT MORE` in a process of its own, without progress bar, plots
    or reports (these tests look at what a run records and how it ends)."""
    return hil_process(
        "run", str(scenario), "--out", str(out), "--no-progress", "--no-reports", *more
    )


def test_injected_commands_on_the_hub_from_a_second_client(tmp_path: Path) -> None:
    port = free_port()
    hub = hil_process("bus", "serve", "--port", str(port))
    try:
        wait_for(lambda: _listening(port), "the hub")
        run = hil_run_process(
            # 20 s: long enough for the intruder to join after the first block is on disk
            # (the recorders flush in blocks of up to 0.25 s), the run being 15-25x real time
            scenario_file(tmp_path, 20.0, HOLD), tmp_path / "run",
            "--bus", f"loopback:127.0.0.1:{port}",
        )  # fmt: skip
        wait_for(lambda: recorded(tmp_path / "run"), "progress")
        from rigbus.canbus import BusSpec, open_bus

        intruder = Intruder(open_bus(BusSpec.parse(f"loopback:{port}")), foreign_command)
        try:
            _, err = run.communicate(timeout=120)
        finally:
            intruder.close()
    finally:
        hub.terminate()
        hub.wait(timeout=10)
    assert run.returncode == 0, err
    s = summary(tmp_path / "run")
    assert s["intrusions"]["count"] > 0 and intruder.sent > 0
    readable(tmp_path / "run")


def _listening(port: int) -> bool:
    with socket.socket() as sock:
        return sock.connect_ex(("127.0.0.1", port)) == 0


# ------------------------------------------------------------------ strict and hold


def test_over_pressure_stops_a_strict_run_and_is_counted_under_hold(tmp_path: Path, capsys) -> None:  # noqa: E501
    low = ("max_pressure = 60000.0", "max_pressure = 12000.0")
    code, lines = run_cli(
        capsys,
        str(scenario_file(tmp_path, 1.0, low)),
        "--inprocess",
        "--out",
        str(tmp_path / "strict"),
    )  # noqa: E501
    assert code == 1 and len(lines) == 1 and "EMCY 0xFF01 (over-pressure)" in lines[0]
    s = summary(tmp_path / "strict")
    assert s["status"] == "failed" and "over-pressure" in s["error"]
    readable(tmp_path / "strict")
    code, _ = run_cli(
        capsys,
        str(scenario_file(tmp_path, 1.0, low, HOLD)),
        "--inprocess",
        "--out",
        str(tmp_path / "hold"),
    )  # noqa: E501
    assert code == 0
    assert any("EMCY" in w for w in summary(tmp_path / "hold")["warnings"])


class SilentAfter(ControllerNode):
    """The real controller that stops commanding after `cycles_ok` cycles (SYNC goes on)."""

    cycles_ok = 20

    def _send(self, frame, sim_time: float) -> None:  # type: ignore[override]
        if isinstance(frame, Sync) or frame.counter < self.cycles_ok:
            super()._send(frame, sim_time)


@pytest.mark.parametrize("policy", ["strict", "hold"])
def test_a_controller_that_stops_commanding(tmp_path: Path, monkeypatch, capsys, policy) -> None:
    monkeypatch.setattr("hil.run.ControllerNode", SilentAfter)
    edits = [HOLD] if policy == "hold" else []
    out = tmp_path / "run"
    code, lines = run_cli(
        capsys, str(scenario_file(tmp_path, 1.0, *edits)), "--inprocess", "--out", str(out)
    )  # noqa: E501
    s = summary(out)
    readable(out)
    if policy == "strict":
        assert code == 1 and len(lines) == 1 and "missed" in lines[0]
        assert s["status"] == "failed" and "SYNC 21" in s["error"]
    else:
        assert code == 0 and s["frames"]["missed"] > 0 and s["frames"]["emcy"] == 1
        assert any("missed" in w for w in s["warnings"])


class StaleAfter(ControllerNode):
    """The real controller whose drive commands, after `cycles_ok` cycles, carry the counter of
    the cycle before (a controller one period behind): every command arrives, stale."""

    cycles_ok = 20

    def _send(self, frame, sim_time: float) -> None:  # type: ignore[override]
        if isinstance(frame, DriveCommand) and frame.counter >= self.cycles_ok:
            frame = dataclasses.replace(frame, counter=frame.counter - 1)
        super()._send(frame, sim_time)


def test_a_stale_command_stops_a_strict_run(tmp_path: Path, monkeypatch, capsys) -> None:
    """Under the strict policy a stale command (present, but of an earlier period) ends the run
    at the SYNC that finds it, as a missed one does."""
    monkeypatch.setattr("hil.run.ControllerNode", StaleAfter)
    out = tmp_path / "run"
    code, lines = run_cli(
        capsys, str(scenario_file(tmp_path, 1.0)), "--inprocess", "--out", str(out)
    )
    s = summary(out)
    readable(out)
    assert code == 1 and len(lines) == 1 and "a drive command was stale" in lines[0]
    assert s["status"] == "failed" and "SYNC 21" in s["error"]


# ------------------------------------------------------------------ real time


def test_realtime_overruns_fail_the_run() -> None:
    """A controller whose cycles take 3 periods each (fake clock): every SYNC is late."""
    scenario = load_scenario(scenario_file_static(0.1))
    config = controller_config(scenario)
    now = [0.0]

    def monotonic() -> float:
        now[0] += 0.03  # every reading of the clock is 3 periods later: a loaded machine
        return now[0]

    clock = RealtimeClock(config.control_period, sleep=lambda s: None, monotonic=monotonic)
    lateness = [clock.wait_for(c) for c in range(11)]
    assert all(late >= 0 for late in lateness) and max(lateness) > config.control_period
    report = {"realtime": True, "cycles": 10, "max_lateness": max(lateness),
              "overruns": sum(late > config.control_period for late in lateness)}  # fmt: skip
    failure = realtime_failure(scenario, report)
    assert failure is not None and "real-time run failed" in failure
    assert realtime_failure(scenario, {**report, "overruns": 0, "max_lateness": 0.001}) is None
    assert realtime_failure(scenario, {**report, "realtime": False}) is None


def scenario_file_static(duration: float) -> Path:
    import tempfile

    folder = Path(tempfile.mkdtemp(prefix="softhil-rt-"))
    return scenario_file(folder, duration)


# ------------------------------------------------------------------ processes and signals


@pytest.mark.parametrize(
    "sig,code,line,status",
    [
        (signal.SIGINT, 130, "hil: interrupted", "interrupted"),
        (signal.SIGTERM, 143, "hil: terminated", "terminated"),
    ],
    ids=["INT", "TERM"],
)
def test_hil_run_signalled(tmp_path: Path, sig, code: int, line: str, status: str) -> None:
    out = tmp_path / "run"
    run = hil_run_process(scenario_file(tmp_path, LONG), out)
    wait_for(lambda: recorded(out), "progress")
    run.send_signal(sig)
    _, err = run.communicate(timeout=60)
    assert run.returncode == code, err
    assert err.strip().splitlines() == [line]
    s = summary(out)
    assert s["status"] == status and s["error"]
    # how far the run got: the rows recorded, and the same in the error's words
    reached = s["reached"]
    assert reached["cycles"] == 10000 and 0 < reached["cycle"] < 10000, reached
    assert reached["time"] == pytest.approx(reached["cycle"] * 0.01)
    assert s["error"] == (
        f"{status} (SIG{sig.name[3:]}) at t = {reached['time']:.3f} s "
        f"(after SYNC {reached['cycle']} of 10000)"
    )
    assert not (out / "controller.pid").exists() and not (out / hil.results.LOCK).exists()
    readable(out)


def test_hil_run_killed_hard_leaves_blocks_that_hil_csv_writes_the_csv_from(
    tmp_path: Path, capsys
) -> None:
    """SIGKILL of `hil run` itself: no CSV (it is written when a run ends), the blocks written
    every 0.25 s stay; `hil csv` writes the CSV of their rows (taking the dead run's lock), one
    row a SYNC from the first, each complete."""
    out = tmp_path / "run"
    run = hil_run_process(scenario_file(tmp_path, LONG), out)
    wait_for(lambda: recorded(out), "progress")
    run.kill()
    run.communicate(timeout=60)
    controller = out / "controller.pid"
    if controller.exists():  # the controller outlives the plant it served: stop it here
        with contextlib.suppress(ProcessLookupError, ValueError):
            os.kill(int(controller.read_text()), signal.SIGKILL)
    assert not (out / "signals.csv").exists() and (out / hil.results.LOCK).exists()
    assert hil_main(["csv", str(out)]) == 0
    printed = capsys.readouterr()
    assert "took over the stale lock" in printed.err and "rows from" in printed.out
    with (out / "signals.csv").open() as file:
        times = [float(row["time"]) for row in csv.DictReader(file)]
    assert len(times) > 2 and times == [round(0.01 * c, 9) for c in range(len(times))]
    assert "signals.csv" in hil.results.manifest_names(out)
    readable(out)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["KILL", "TERM"])
def test_controller_killed(tmp_path: Path, sig) -> None:
    out = tmp_path / "run"
    run = hil_run_process(scenario_file(tmp_path, LONG), out)
    wait_for(lambda: recorded(out) and rows(out / "controller.pid") > 0, "progress")  # noqa: E501
    os.kill(int((out / "controller.pid").read_text()), sig)
    _, err = run.communicate(timeout=60)
    assert run.returncode == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "the controller exited with code" in lines[0], err
    s = summary(out)
    assert s["status"] == "failed" and "controller exited" in s["error"]
    assert s["error"].endswith(f"stopped at t = {s['reached']['time']:.3f} s (after SYNC "
                               f"{s['reached']['cycle']} of 10000)")  # fmt: skip
    readable(out)


def test_controller_frozen_times_out(tmp_path: Path) -> None:
    out = tmp_path / "run"
    short_wait = ('policy = "strict"', 'policy = "strict"\ntimeout = 0.5')
    run = hil_run_process(scenario_file(tmp_path, LONG, short_wait), out)
    wait_for(lambda: recorded(out) and rows(out / "controller.pid") > 0, "progress")  # noqa: E501
    pid = int((out / "controller.pid").read_text())
    os.kill(pid, signal.SIGSTOP)
    try:
        _, err = run.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)
    assert run.returncode == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "no frame from the controller for 0.5 s" in lines[0], err
    assert summary(out)["status"] == "failed"
    assert not (out / "controller.pid").exists()
    readable(out)


def test_hub_killed_under_a_running_plant(tmp_path: Path) -> None:
    port = free_port()
    hub = hil_process("bus", "serve", "--port", str(port))
    wait_for(lambda: _listening(port), "the hub")
    out = tmp_path / "run"
    run = hil_run_process(scenario_file(tmp_path, LONG), out, "--bus", f"loopback:127.0.0.1:{port}")
    wait_for(lambda: recorded(out), "progress")
    hub.kill()
    hub.wait(timeout=10)
    _, err = run.communicate(timeout=60)
    assert run.returncode == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hil: error: "), err
    s = summary(out)
    assert s["status"] == "failed" and s["error"]
    assert "Traceback" not in (out / "controller.log").read_text()
    readable(out)


def test_fmu_error_mid_run(tmp_path: Path, capsys) -> None:
    """A connection that drives the segment's piston input beyond its stroke once the piston
    moves: the FMU answers fmi2Error mid-run."""
    path = scenario_file(tmp_path, 2.0)
    path.write_text(
        path.read_text() + '\n[[connections]]\nfrom = "cylinder1.x"\nto = "segment1.x_piston"\n'
        "gain = 5.0\noffset = -0.1\n"
    )
    out = tmp_path / "run"
    code, lines = run_cli(capsys, str(path), "--inprocess", "--out", str(out))
    assert code == 1 and len(lines) == 1 and "fmi2DoStep" in lines[0] and "x_piston" in lines[0]
    s = summary(out)
    assert s["status"] == "failed" and "outside the stroke" in s["error"]
    assert readable(out) > 0


def test_fmu_error_mid_run_is_the_same_with_the_controller_as_a_process(
    tmp_path: Path, capsys
) -> None:
    """With the controller in its own process the plant steps each period while the controller
    computes (Plant._step_ahead); an FMU that fails there must fail the run where the in-process
    run fails: the same error, the same recorded signals and CAN log, frame for frame (the
    controller's commands of the last period included)."""
    path = scenario_file(tmp_path, 2.0)
    path.write_text(
        path.read_text() + '\n[[connections]]\nfrom = "cylinder1.x"\nto = "segment1.x_piston"\n'
        "gain = 5.0\noffset = -0.1\n"
    )
    results = {}
    for mode in ("--inprocess", None):
        out = tmp_path / (mode or "process").strip("-")
        code, lines = run_cli(capsys, str(path), *([mode] if mode else []), "--out", str(out))
        assert code == 1 and len(lines) == 1 and "fmi2DoStep" in lines[0], lines
        recorded = (out / "signals.csv").read_bytes(), (out / "can.log").read_bytes()
        results[mode] = (lines[0], *recorded)
    (error_a, signals_a, log_a), (error_b, signals_b, log_b) = results.values()
    assert error_a == error_b
    assert signals_a == signals_b
    assert log_a == log_b
    # the log ends with the failing period's SYNC, after the commands the controller sent for it
    last = log_a.decode().splitlines()[-3:]
    assert " 201#" in last[0] and last[0].endswith(" R")
    assert " 080#" in last[-1] and last[-1].endswith(" R")


def test_realtime_run_late_on_a_loaded_machine_fails(tmp_path: Path, capsys, monkeypatch) -> None:
    """The real-time clock reads a machine so loaded that each cycle takes 3 periods."""
    now = [0.0]

    def monotonic() -> float:
        now[0] += 0.03
        return now[0]

    monkeypatch.setattr(
        "hil.run.RealtimeClock",
        lambda period: RealtimeClock(period, sleep=lambda s: None, monotonic=monotonic),
    )
    out = tmp_path / "run"
    code, lines = run_cli(
        capsys, str(scenario_file(tmp_path, 0.3)), "--inprocess", "--realtime", "--out", str(out)
    )  # noqa: E501
    assert code == 1 and len(lines) == 1 and "real-time run failed" in lines[0]
    s = summary(out)
    assert s["status"] == "failed" and "SYNCs were more than one control period" in s["error"]
    assert s["controller"]["overruns"] > 0


def test_a_failed_send_keeps_the_syncs_row_and_frames(
    tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The bus fails as the plant sends SYNC 7's frames: the run fails with one line naming the
    frames, and what was recorded stays, SYNC 7's signal row and its SYNC frame included."""
    import hil.plant

    sends = [0]
    real_send_all = hil.plant.send_all

    def failing(bus: can.BusABC, messages: list[can.Message]) -> None:
        sends[0] += 1
        if sends[0] == 8:  # SYNC 0..6 answered, SYNC 7's frames fail
            raise can.CanOperationError("the transceiver is gone")
        real_send_all(bus, messages)

    monkeypatch.setattr(hil.plant, "send_all", failing)
    out = tmp_path / "run"
    code, lines = run_cli(
        capsys, str(scenario_file(tmp_path, 1.0)), "--inprocess", "--out", str(out)
    )
    assert code == 1 and len(lines) == 1 and "sending 0x" in lines[0], lines
    assert "the transceiver is gone" in lines[0]
    with (out / "signals.csv").open() as file:
        times = [float(row["time"]) for row in csv.DictReader(file)]
    assert times == [round(0.01 * c, 9) for c in range(8)]
    log = (out / "can.log").read_text().splitlines()
    assert " 080#07 R" in log[-1]  # SYNC 7 received, none of its answers sent
    readable(out)
