"""Tests for the stepping kernel (hil/cosim/kernel): the C inner loop against the Python master.

The Python master is the reference. The same coupled system (two segments of DriveCylinder and
FeaSegment, one FMU at decimation 2, a connection with gain and offset, a Python probe stepping at
decimation 10 between two FMUs, a device node whose outputs change only when published at SYNC)
runs once per path; every value must be bit-identical at every comparison point.
"""

from __future__ import annotations

import contextlib
import json
import math
import subprocess
import sys
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from time import perf_counter

import pytest

from hil.cosim import Algorithm, Connection, FmuParticipant
from hil.environment import kernel_thread
from hil.errors import FmuError, HilError
from hil.fmu.build import BuiltFmu
from hil.fmu.slave import FmuSlave
from hil.run import RunOptions, run_scenario
from hil.scenario import load_scenario

H = 1e-3
SYNC_TICKS = 10


class Probe:
    """A Python participant at decimation 10: reads cylinder1.x, outputs a setpoint for
    cylinder2 that follows it (so a Python step feeds an FMU input)."""

    name = "probe"
    decimation = 10

    def __init__(self) -> None:
        self.x = 0.0
        self.received: list[tuple[float, dict[str, float]]] = []
        self.target = 0.025

    def input_names(self) -> list[str]:
        return ["x"]

    def output_names(self) -> list[str]:
        return ["x_ref"]

    def set_inputs(self, values: Mapping[str, float]) -> None:
        self.x = values["x"]

    def step(self, time: float, step: float) -> None:
        self.received.append((time, {"x": self.x}))
        self.target = 0.03 - 0.5 * (self.x - 0.025)

    def get_outputs(self) -> dict[str, float]:
        return {"x_ref": self.target}


class Firmware:
    """A device node: holds its setpoint between SYNCs; the test changes it and publishes."""

    name = "drive"
    decimation = 1
    outputs_hold = True  # its step never changes its outputs (the master may step it late)

    def __init__(self) -> None:
        self.setpoint = 0.025

    def input_names(self) -> list[str]:
        return ["x"]

    def output_names(self) -> list[str]:
        return ["x_ref"]

    def set_inputs(self, values: Mapping[str, float]) -> None:
        pass

    def step(self, time: float, step: float) -> None:
        pass

    def get_outputs(self) -> dict[str, float]:
        return {"x_ref": self.setpoint}


def setpoint(sync: int) -> float:
    """The firmware's setpoint from SYNC `sync` on: steps that make both cylinders move."""
    return (0.025, 0.035, 0.015, 0.03)[(sync // 8) % 4]


class Sampler:
    """A Python participant with no outputs (as the camera): it records what it reads at its
    ticks, at decimation 3, so it is due inside every SYNC period."""

    name = "sampler"
    decimation = 3

    def __init__(self) -> None:
        self.inputs: dict[str, float] = {}
        self.received: list[tuple[float, dict[str, float]]] = []

    def input_names(self) -> list[str]:
        return ["x", "kappa"]

    def output_names(self) -> list[str]:
        return []

    def set_inputs(self, values: Mapping[str, float]) -> None:
        self.inputs = dict(values)

    def step(self, time: float, step: float) -> None:
        self.received.append((time, self.inputs))

    def get_outputs(self) -> dict[str, float]:
        return {}


def coupled(
    cylinder: BuiltFmu,
    segment: BuiltFmu,
    kernel: bool,
    firmware_decimation: int = 1,
    probe_decimation: int = 10,
    piston_offset: float = 0.0,
) -> tuple[Algorithm, Probe, Firmware, list[FmuSlave]]:
    """The coupled rig; `firmware_decimation` SYNC_TICKS (the device nodes' own) lets the
    worker thread step whole periods, 1 keeps it off (outputs due at every tick);
    `piston_offset` [m] shifts what segment 1 is told of its piston (far enough, and the
    piston's move drives it out of the stroke: an FMU error inside a period)."""
    slaves = []
    participants: list = []
    for n in (1, 2):
        c = FmuSlave(cylinder, f"cylinder{n}")
        s = FmuSlave(segment, f"segment{n}")
        slaves += [c, s]
        participants += [FmuParticipant(c), FmuParticipant(s, decimation=2 if n == 1 else 1)]
    probe, firmware = Probe(), Firmware()
    probe.decimation = probe_decimation
    firmware.decimation = firmware_decimation
    participants += [probe, firmware, Sampler()]
    connections = [
        Connection("cylinder2.x", "sampler.x"),
        Connection("segment1.kappa", "sampler.kappa", gain=-2.0, offset=0.5),
        Connection("drive.x_ref", "cylinder1.x_ref"),
        Connection("cylinder1.x", "drive.x"),
        Connection("cylinder1.x", "probe.x"),
        Connection("probe.x_ref", "cylinder2.x_ref"),
        # a gain and an offset on a pressure: the order of the two roundings is tested
        Connection("segment1.p_b", "cylinder1.p_b", gain=0.9, offset=137.5),
    ]
    for n in (1, 2):
        connections += [
            Connection(f"cylinder{n}.x", f"segment{n}.x_piston", offset=piston_offset * (n == 1)),
            Connection(f"segment{n}.p_a", f"cylinder{n}.p_a"),
        ]
    connections.append(Connection("segment2.p_b", "cylinder2.p_b"))
    master = Algorithm(participants, connections, H, kernel=kernel)
    master.set_input("segment2", "tau_ext", 0.002)
    return master, probe, firmware, slaves


def run_syncs(
    cylinder: BuiltFmu,
    segment: BuiltFmu,
    kernel: bool,
    syncs: int,
    advance: Callable[[Algorithm, int], None] | None = None,
    firmware_decimation: int = 1,
    after_sync: Callable[[Algorithm, int], None] | None = None,
    probe_decimation: int = 10,
) -> tuple[list[dict[str, float]], Probe, bool]:
    master, probe, firmware, slaves = coupled(
        cylinder, segment, kernel, firmware_decimation, probe_decimation
    )
    history = []
    try:
        for sync in range(1, syncs + 1):
            if advance is None:
                master.advance_to(sync * SYNC_TICKS)
            else:
                advance(master, sync * SYNC_TICKS)
            history.append({**master.values, **master.inputs_of("drive")})
            firmware.setpoint = setpoint(sync)
            master.publish("drive")
            if sync == syncs // 2:
                master.set_input("segment2", "tau_ext", -0.001)
            if after_sync is not None:
                after_sync(master, sync * SYNC_TICKS)
        used = master.uses_kernel
        probe.sampled = master.participants["sampler"].received  # type: ignore[attr-defined]
    finally:
        master.settle()
        for slave in slaves:
            slave.close()
    return history, probe, used


def test_kernel_and_python_master_are_bit_identical_at_every_sync(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu
) -> None:
    python, python_probe, used = run_syncs(drive_cylinder_fmu, fea_segment_fmu, False, 60)
    assert not used
    kernel, kernel_probe, used = run_syncs(drive_cylinder_fmu, fea_segment_fmu, True, 60)
    assert used
    assert kernel == python  # == on floats: bit-identical (no NaN here)
    assert kernel_probe.received == python_probe.received
    assert kernel_probe.sampled == python_probe.sampled  # type: ignore[attr-defined]
    # the comparison means something: the pistons and pressures moved
    for key in ("cylinder1.x", "cylinder2.x", "segment1.p_b", "segment2.kappa"):
        assert len({row[key] for row in python}) > 20, key
    assert [t for t, _ in python_probe.received] == [k * H for k in range(0, 600, 10)]


def test_what_the_loop_reads_after_the_worker_is_what_values_says(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu
) -> None:
    """After a period on the worker thread the master copies the FMUs' values into `values`
    only when asked; what the plant's loop reads before that (`reader`, `inputs_of`: from the
    kernel's array, a published value as published) is what the Python master holds, and what
    `values` then says."""
    keys = ["segment1.kappa", "drive.x_ref", "cylinder2.x", "probe.x_ref", "segment2.p_b"]
    reads: dict[bool, list[object]] = {False: [], True: []}
    stale: list[bool] = []

    def ahead(master: Algorithm, target: int) -> None:
        read = master.__dict__.setdefault("_test_read", master.reader(keys))
        one = master.__dict__.setdefault("_test_one", master.reader(["cylinder1.x"]))
        if master.uses_kernel:
            assert master.start_advance(target, 0.0)
        master.advance_to(target)
        stale.append(master._stale)
        got = (read(), one(), master.inputs_of("drive"), master.inputs_of("sampler"))
        assert got[0] == tuple(master.values[k] for k in keys)
        assert got[1] == (master.values["cylinder1.x"],)
        reads[master.uses_kernel].append(got)

    python, _, _ = run_syncs(drive_cylinder_fmu, fea_segment_fmu, False, 20, ahead, SYNC_TICKS)
    kernel, _, used = run_syncs(drive_cylinder_fmu, fea_segment_fmu, True, 20, ahead, SYNC_TICKS)
    assert used and kernel == python
    assert reads[True] == reads[False]
    assert stale.count(True) == 20  # the kernel's reads all came from its array
    assert len({got[0] for got in reads[True]}) > 10  # the values moved
    with pytest.raises(HilError, match="no value 'segment1.nope'"):
        Algorithm([], [], H).reader(["segment1.nope"])


class Watcher:
    """A Python participant with no outputs that reads a device node's output (published) and
    an FMU's: what it is given must be what the Python master gives it."""

    name = "watcher"
    decimation = SYNC_TICKS

    def input_names(self) -> list[str]:
        return ["x_ref", "kappa"]

    def output_names(self) -> list[str]:
        return []

    def set_inputs(self, values: Mapping[str, float]) -> None:
        pass

    def step(self, time: float, step: float) -> None:
        pass

    def get_outputs(self) -> dict[str, float]:
        return {}


def test_every_reader_after_a_period_in_c_sees_the_python_masters_values(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu
) -> None:
    """After a period on the worker thread the master's mapping is brought up to date only when
    read. Whatever reads first sees what the Python master holds: a participant's inputs after a
    device node published (from the kernel's array), an observer added at once, and an observer
    appended to `observers` directly, whose ticks then run in Python."""

    class Recorder:
        def __init__(self) -> None:
            self.calls: list[tuple[int, dict[str, float]]] = []

        def observe(self, tick: int, values: Mapping[str, float]) -> None:
            self.calls.append((tick, dict(values)))

    def run(kernel: bool) -> tuple[list[object], list[object], bool]:
        with (
            FmuSlave(drive_cylinder_fmu, "cylinder1") as cylinder,
            FmuSlave(fea_segment_fmu, "segment1") as segment,
        ):
            firmware = Firmware()
            firmware.decimation = SYNC_TICKS
            participants = [FmuParticipant(cylinder), FmuParticipant(segment), firmware, Watcher()]
            connections = [
                Connection("drive.x_ref", "cylinder1.x_ref"),
                Connection("cylinder1.x", "drive.x"),
                Connection("cylinder1.x", "segment1.x_piston"),
                Connection("segment1.p_a", "cylinder1.p_a"),
                Connection("segment1.p_b", "cylinder1.p_b"),
                Connection("drive.x_ref", "watcher.x_ref", gain=2.0),
                Connection("segment1.kappa", "watcher.kappa"),
            ]
            master = Algorithm(participants, connections, H, kernel=kernel)
            seen: list[object] = []
            for sync in range(1, 13):
                if kernel:
                    assert master.start_advance(sync * SYNC_TICKS, 0.0)
                master.advance_to(sync * SYNC_TICKS)
                seen.append(master.inputs_of("watcher"))
                firmware.setpoint = 0.02 + 0.001 * sync
                master.publish("drive")
                seen.append(master.inputs_of("watcher"))  # the setpoint just published
            first, direct = Recorder(), Recorder()
            master.add_observer(first)  # right after a period: no read in between
            master.observers.clear()
            if kernel:
                assert master.start_advance(13 * SYNC_TICKS, 0.0)
            master.advance_to(13 * SYNC_TICKS)
            master.observers.append(direct)  # not through add_observer: nothing refreshed
            master.advance_to(13 * SYNC_TICKS + 4)  # these ticks in Python
            used = master.uses_kernel
            master.settle()
            return seen, [first.calls, direct.calls, dict(master.values)], used

    python = run(False)
    kernel = run(True)
    assert not python[2] and kernel[2]
    assert kernel[0] == python[0]
    assert kernel[1] == python[1]
    assert len({str(inputs) for inputs in python[0]}) > 12  # the values moved


@pytest.mark.parametrize("thread", [True, False])
@pytest.mark.parametrize("decimation", [1, 3, 7])
def test_observers_inside_a_period_on_the_worker_see_the_sampled_ticks(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu, decimation: int, thread: bool
) -> None:
    """An observer of every `decimation`-th tick while the FMUs step whole periods, on the
    kernel's worker thread (`thread`) or in turn (the kernel stopping at the observer's ticks,
    no Python participant due in between): it sees, at exactly its ticks, the values the Python
    path shows at those ticks, and the periods still start on the thread."""

    class Recorder:
        def __init__(self) -> None:
            self.decimation = decimation
            self.calls: list[tuple[int, dict[str, float]]] = []

        def observe(self, tick: int, values: Mapping[str, float]) -> None:
            self.calls.append((tick, dict(values)))

    recorders = {False: Recorder(), True: Recorder()}
    started: list[bool] = []

    def ahead(master: Algorithm, target: int) -> None:
        if not master.observers:
            master.add_observer(recorders[master.uses_kernel])
        if master.uses_kernel and thread:
            started.append(master.start_advance(target, 0.0))
        master.advance_to(target)

    python, _, _ = run_syncs(
        drive_cylinder_fmu, fea_segment_fmu, False, 12, ahead, firmware_decimation=SYNC_TICKS
    )
    kernel, _, _ = run_syncs(
        drive_cylinder_fmu, fea_segment_fmu, True, 12, ahead, firmware_decimation=SYNC_TICKS
    )
    assert started == [True] * 12 * thread
    assert kernel == python
    got, want = recorders[True].calls, recorders[False].calls
    # at the tick it was added (0), then every decimation-th tick up to the last SYNC's 120
    assert [t for t, _ in want] == [0, *range(decimation, 121, decimation)]
    assert [t for t, _ in got] == [t for t, _ in want]
    assert got == want
    assert len({row["segment1.kappa"] for _, row in want}) > 5  # the values moved


def test_kernel_and_python_master_are_bit_identical_at_every_tick(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu
) -> None:
    ticks: dict[bool, list[dict[str, float]]] = {False: [], True: []}

    def tick_by_tick(master: Algorithm, target: int) -> None:
        while master.tick < target:
            master.advance_to(master.tick + 1)
            ticks[master.uses_kernel].append(dict(master.values))

    python, _, _ = run_syncs(drive_cylinder_fmu, fea_segment_fmu, False, 12, tick_by_tick)
    kernel, _, _ = run_syncs(drive_cylinder_fmu, fea_segment_fmu, True, 12, tick_by_tick)
    assert len(ticks[True]) == 120
    assert ticks[True] == ticks[False]
    assert kernel == python


def test_observers_keep_the_kernel_and_see_what_the_python_path_shows(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu
) -> None:
    class Recorder:
        def __init__(self) -> None:
            self.calls: list[tuple[int, dict[str, float]]] = []

        def observe(self, tick: int, values: Mapping[str, float]) -> None:
            self.calls.append((tick, dict(values)))

    def observed(master: Algorithm, target: int) -> None:
        # the periods ending at SYNC 2 and 33 run with an observer of every tick: the kernel
        # stops at each tick for it (it is not switched off), and the observer sees at every
        # tick what the Python path shows it.
        recorder = recorders[master.uses_kernel]
        if target in (20, 330):
            master.add_observer(recorder)
        master.advance_to(target)
        master.observers.clear()

    recorders = {False: Recorder(), True: Recorder()}
    seconds: list[float] = []

    def timed(master: Algorithm, target: int) -> None:
        before = master.kernel_seconds
        observed(master, target)
        if master.uses_kernel and target in (20, 330):
            seconds.append(master.kernel_seconds - before)

    python, _, _ = run_syncs(drive_cylinder_fmu, fea_segment_fmu, False, 40, observed)
    kernel, _, used = run_syncs(drive_cylinder_fmu, fea_segment_fmu, True, 40, timed)
    assert used
    assert len(seconds) == 2 and all(s > 0.0 for s in seconds)  # observed periods stepped in C
    assert recorders[True].calls == recorders[False].calls
    expected = [*range(10, 21), *range(320, 331)]
    assert [tick for tick, _ in recorders[True].calls] == expected
    assert setpoint(1) == setpoint(32) != setpoint(31)
    assert kernel == python


def test_environment_variable_and_argument_select_the_python_path(
    drive_cylinder_fmu: BuiltFmu, monkeypatch: pytest.MonkeyPatch
) -> None:
    with FmuSlave(drive_cylinder_fmu, "cylinder1") as slave:
        participants = [FmuParticipant(slave)]
        monkeypatch.delenv("SOFTHIL_KERNEL", raising=False)
        assert Algorithm(participants, [], H).uses_kernel
        assert not Algorithm(participants, [], H, kernel=False).uses_kernel
        monkeypatch.setenv("SOFTHIL_KERNEL", "0")
        master = Algorithm(participants, [], H)
        assert not master.uses_kernel
        master.advance_to(3)
        assert master.tick == 3
        monkeypatch.setenv("SOFTHIL_KERNEL", "1")
        assert Algorithm(participants, [], H).uses_kernel
        for value in ("yes", "off", "2", ""):  # a misspelt switch is not silently "on"
            monkeypatch.setenv("SOFTHIL_KERNEL", value)
            with pytest.raises(HilError, match=rf"^SOFTHIL_KERNEL='{value}': must be 1 .* or 0"):
                Algorithm(participants, [], H)


def test_master_without_fmus_does_not_use_the_kernel() -> None:
    assert not Algorithm([Probe()], [], H, kernel=True).uses_kernel


def failing_run(cylinder: BuiltFmu, segment: BuiltFmu, kernel: bool) -> tuple[str, int]:
    master, _, _, slaves = coupled(cylinder, segment, kernel)
    try:
        master.advance_to(25)
        master.set_input("segment2", "tau_ext", math.nan)
        with pytest.raises(FmuError) as info:
            master.advance_to(40)
        return str(info.value), master.tick
    finally:
        for slave in slaves:
            slave.close()


def test_fmu_error_inside_the_kernel_is_the_python_paths_fmu_error(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu
) -> None:
    python = failing_run(drive_cylinder_fmu, fea_segment_fmu, False)
    kernel = failing_run(drive_cylinder_fmu, fea_segment_fmu, True)
    assert kernel == python
    message, tick = kernel
    assert tick == 25
    assert "\n" not in message
    assert message.startswith("segment2 (FeaSegment): fmi2SetReal failed: ")
    assert "non-finite" in message


def test_a_closed_instance_is_an_error_not_a_crash(drive_cylinder_fmu: BuiltFmu) -> None:
    slave = FmuSlave(drive_cylinder_fmu, "cylinder1")
    master = Algorithm([FmuParticipant(slave)], [], H, kernel=True)
    master.advance_to(2)
    slave.close()
    with pytest.raises(FmuError, match=r"^cylinder1: the FMU instance is closed$"):
        master.advance_to(4)
    assert master.tick == 2


def test_closed_loop_files_are_identical_with_and_without_the_kernel(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The whole rig (drive firmware publishing at SYNC, the camera at its rate, two segments)
    over the bus: the CAN log and the signals do not depend on the path."""
    scenario = load_scenario()
    scenario = replace(scenario, duration=1.0, robot=replace(scenario.robot, segments=2), seed=3)
    files = {}
    threads = os_threads()
    started: list[bool] = []
    real = Algorithm.start_advance

    def spy(self: Algorithm, tick: int, spin: float = 0.0) -> bool:
        started.append(real(self, tick, spin))
        return started[-1]

    monkeypatch.setattr(Algorithm, "start_advance", spy)
    # the Python path, the kernel in turn with the controller, the kernel on its worker thread
    for kernel, worker in (("0", "0"), ("1", "0"), ("1", "1")):
        monkeypatch.setenv("SOFTHIL_KERNEL", kernel)
        monkeypatch.setenv("SOFTHIL_KERNEL_THREAD", worker)
        out = tmp_path / f"{kernel}{worker}"
        started.clear()
        run_scenario(scenario, RunOptions(out=out, inprocess=True, progress=False, reports=False))
        # every period (after SYNC 0 .. after the last SYNC but one) on the thread, where on
        assert started == ([True] * scenario.cycles if worker == "1" else []), worker
        summary = json.loads((out / "summary.json").read_text())
        assert summary["periods_on_kernel_thread"] == len(started)
        files[kernel + worker] = {
            name: (out / name).read_bytes() for name in ("can.log", "signals.csv")
        }
        assert os_threads() == threads  # the worker thread ends with the run
    assert files["11"] == files["10"] == files["00"]
    assert len(files["11"]["signals.csv"].splitlines()) > 90


def test_a_camera_with_jitter_steps_every_tick_and_the_files_stay_identical(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With exposure jitter the camera is due at every tick (decimation 1): the worker samples
    every tick of the period for it."""
    scenario = load_scenario()
    camera = replace(scenario.camera, jitter=0.0005)
    scenario = replace(scenario, duration=0.5, camera=camera, seed=5)
    files = {}
    for worker in ("0", "1"):
        monkeypatch.setenv("SOFTHIL_KERNEL_THREAD", worker)
        out = tmp_path / worker
        run_scenario(scenario, RunOptions(out=out, inprocess=True, progress=False, reports=False))
        files[worker] = {name: (out / name).read_bytes() for name in ("can.log", "signals.csv")}
    assert files["1"] == files["0"]
    assert files["1"]["can.log"].count(b" 281#") > 40  # camera frames were sent


def os_threads() -> int:
    """This process's kernel worker threads, by the name the kernel gives them (a C thread,
    which `threading` does not list)."""
    count = 0
    for task in Path("/proc/self/task").iterdir():
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            count += (task / "comm").read_text().strip() == "softhil-kernel"
    return count


@pytest.mark.parametrize(
    ("firmware_decimation", "probe_decimation", "thread"),
    [(SYNC_TICKS, SYNC_TICKS, True), (1, SYNC_TICKS, True), (SYNC_TICKS, 5, False)],
)
def test_stepping_ahead_on_the_worker_thread_is_bit_identical(
    drive_cylinder_fmu: BuiltFmu,
    fea_segment_fmu: BuiltFmu,
    firmware_decimation: int,
    probe_decimation: int,
    thread: bool,
) -> None:
    """start_advance at every SYNC, then the SYNC's own calls (publish, inputs_of) wait for it:
    every value, what the probe read at its ticks (its first tick stepped in turn: its step
    changes its outputs) and what the sampler and the firmware read inside each period (from
    the values the worker sampled) as in the Python master. The firmware holds its outputs, so
    it may be stepped late even at every tick; the probe, due inside a period (decimation 5),
    declines the thread and nothing changes."""
    started = []

    def ahead(master: Algorithm, tick: int) -> None:
        # after the SYNC's work (publish, set_input): the next period on the worker thread;
        # the next SYNC's advance_to waits for it (none after the last SYNC, as in the plant)
        if tick == 40 * SYNC_TICKS:
            return
        started.append(master.start_advance(tick + SYNC_TICKS, 0.0))
        if not started[-1]:
            assert master.tick == tick  # declined: nothing stepped

    python, python_probe, _ = run_syncs(
        drive_cylinder_fmu,
        fea_segment_fmu,
        False,
        40,
        firmware_decimation=firmware_decimation,
        probe_decimation=probe_decimation,
    )
    kernel, kernel_probe, used = run_syncs(
        drive_cylinder_fmu,
        fea_segment_fmu,
        True,
        40,
        None,
        firmware_decimation,
        ahead,
        probe_decimation,
    )
    assert used
    assert all(started) if thread else not any(started)
    assert kernel == python
    assert kernel_probe.received == python_probe.received
    assert len(python_probe.received) == 400 // probe_decimation
    assert kernel_probe.sampled == python_probe.sampled  # type: ignore[attr-defined]
    assert [t for t, _ in python_probe.sampled] == [k * H for k in range(0, 400, 3)]  # type: ignore[attr-defined]
    assert len({inputs["kappa"] for _, inputs in python_probe.sampled}) > 50  # type: ignore[attr-defined]


def test_stepping_ahead_fails_as_the_python_path_fails(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu
) -> None:
    """An FMU error on the worker thread is raised where advance_to would raise it, with the
    same message and the same tick reached; the samplers due before it were stepped."""

    def failing(ahead: bool) -> tuple[str, int, list[tuple[float, dict[str, float]]]]:
        master, _, _, slaves = coupled(
            drive_cylinder_fmu, fea_segment_fmu, True, SYNC_TICKS, probe_decimation=40
        )
        try:
            master.advance_to(20)
            master.set_input("segment2", "tau_ext", math.nan)
            if ahead:
                assert master.start_advance(30, 0.0)
            with pytest.raises(FmuError) as info:
                master.advance_to(30)
            return str(info.value), master.tick, master.participants["sampler"].received  # type: ignore[attr-defined]
        finally:
            master.settle()
            for slave in slaves:
                slave.close()

    assert failing(True) == failing(False)
    message, tick, sampled = failing(True)
    assert tick == 20
    assert message.startswith("segment2 (FeaSegment): fmi2SetReal failed: ")
    assert [t for t, _ in sampled][-1] == 18 * H


def test_an_fmu_error_at_a_periods_first_tick_steps_no_participant_early(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu
) -> None:
    """The probe (its step changes its outputs) is due at the period's first tick, where an FMU
    fails: start_advance steps that tick in turn, FMUs first, so the probe is not stepped on
    the failing tick, as in advance_to (a review found it stepped before the FMUs)."""

    def failing(ahead: bool) -> tuple[str, int, list[tuple[float, dict[str, float]]], list]:
        master, probe, _, slaves = coupled(drive_cylinder_fmu, fea_segment_fmu, True, SYNC_TICKS)
        try:
            master.advance_to(20)
            master.set_input("segment2", "tau_ext", math.nan)
            with pytest.raises(FmuError) as info:
                if ahead:
                    master.start_advance(30, 0.0)
                master.advance_to(30)
            sampled = master.participants["sampler"].received  # type: ignore[attr-defined]
            return str(info.value), master.tick, probe.received, sampled
        finally:
            master.settle()
            for slave in slaves:
                slave.close()

    ahead = failing(True)
    assert ahead == failing(False)
    assert ahead[1] == 20
    assert [t for t, _ in ahead[2]] == [0.0, 0.01]


def test_stopping_the_worker_during_a_job_waits_for_it() -> None:
    """An interrupt between starting a job and waiting for it leaves the job to `stop` (from
    settle, or closing an FMU): it waits for the job and ends the thread instead of hanging
    (the job's end overwrote the stop, and the thread waited for ever). In a child process,
    so that a hang fails the test instead of the suite."""
    script = """
import time
from hil.fmu.build import build_fmu
from hil.fmu.slave import FmuSlave
from hil.cosim import Algorithm, FmuParticipant

slave = FmuSlave(build_fmu("DriveCylinder"), "cylinder1")
master = Algorithm([FmuParticipant(slave)], [], 1e-3, kernel=True)
assert master.start_advance(2_000_000, 0.0)
time.sleep(0.2)  # the worker has taken the job (a stop before that ends the thread at once)
master._kernel.stop()  # as after an interrupt: no finish
slave.close()
print("stopped")
"""
    result = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).parent.parent,
    )
    assert result.stdout.strip() == "stopped", result.stderr[-2000:]


def test_an_fmu_error_inside_a_period_on_the_worker_thread_is_the_python_paths(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu
) -> None:
    """Segment 1 told its piston 24.5 mm further out fails when the piston's move takes it past
    the stroke, at a tick inside a period: the same message, tick and sampler readings (the
    sampler due at every tick, those before the failing tick stepped) as in turn."""

    def failing(ahead: bool) -> tuple[str, int, list[tuple[float, dict[str, float]]]]:
        master, _, firmware, slaves = coupled(
            drive_cylinder_fmu, fea_segment_fmu, True, SYNC_TICKS, 1000, piston_offset=0.0245
        )
        sampler = master.participants["sampler"]
        sampler.decimation = 1  # type: ignore[misc]
        try:
            with pytest.raises(FmuError) as info:
                for sync in range(1, 100):
                    master.advance_to(sync * SYNC_TICKS)
                    firmware.setpoint = 0.02 + 0.001 * sync
                    master.publish("drive")
                    if ahead:
                        assert master.start_advance((sync + 1) * SYNC_TICKS, 0.0)
            return str(info.value), master.tick, sampler.received  # type: ignore[attr-defined]
        finally:
            master.settle()
            for slave in slaves:
                slave.close()

    message, tick, sampled = failing(True)
    assert (message, tick, sampled) == failing(False)
    assert tick % SYNC_TICKS not in (0, 1)  # inside a period
    assert "x_piston" in message, message
    assert [t for t, _ in sampled][-1] == pytest.approx((tick - 1) * H)


def test_a_participant_with_outputs_due_inside_the_period_declines_the_worker(
    drive_cylinder_fmu: BuiltFmu,
) -> None:
    """The probe (outputs feeding an FMU) at decimation 3: an interval holding one of its
    ticks after the first is stepped in turn; one holding it at its first tick only is not."""
    with FmuSlave(drive_cylinder_fmu, "cylinder2") as slave:
        probe = Probe()
        probe.decimation = 3
        master = Algorithm(
            [FmuParticipant(slave), probe],
            [Connection("probe.x_ref", "cylinder2.x_ref"), Connection("cylinder2.x", "probe.x")],
            H,
            kernel=True,
        )
        master.advance_to(2)
        assert not master.start_advance(4, 0.0)  # probe due at 3
        assert master.tick == 2
        master.advance_to(3)
        assert master.start_advance(6, 0.0)  # probe due at 3 only: stepped first, in turn
        master.advance_to(6)
        assert master.tick == 6
        master.settle()


def test_the_worker_thread_stops_when_settled(drive_cylinder_fmu: BuiltFmu) -> None:
    with FmuSlave(drive_cylinder_fmu, "cylinder1") as slave:
        master = Algorithm([FmuParticipant(slave)], [], H, kernel=True)
        before = os_threads()
        assert master.start_advance(10, 0.0)
        assert os_threads() == before + 1
        master.advance_to(10)
        assert master.tick == 10
        assert master.start_advance(20, 0.0)  # the same thread: one job after the other
        assert os_threads() == before + 1
        master.settle()  # waits for the job, then stops the thread
        assert master.tick == 20
        assert os_threads() == before
        assert not Algorithm([FmuParticipant(slave)], [], H, kernel=False).start_advance(30)


@pytest.mark.parametrize("spin, gap", [(0.0, 0.0), (0.002, 0.0), (0.002, 0.01)])
def test_the_worker_takes_jobs_whether_it_polls_or_sleeps(
    drive_cylinder_fmu: BuiltFmu, spin: float, gap: float
) -> None:
    """Either side polls for the other for `spin` [s], then sleeps, and is woken only if it
    sleeps: jobs handed over while the worker polls (no gap), after it fell asleep (a gap longer
    than its spin) or with no polling at all are all done, and the values are the Python
    master's."""
    import time

    with FmuSlave(drive_cylinder_fmu, "cylinder1") as slave:
        master = Algorithm([FmuParticipant(slave)], [], H, kernel=True)
        for k in range(1, 16):
            assert master.start_advance(10 * k, spin)
            time.sleep(gap)
            master.advance_to(10 * k)  # waits for the job
        threaded = dict(master.values)
        master.settle()
    with FmuSlave(drive_cylinder_fmu, "cylinder1") as slave:
        master = Algorithm([FmuParticipant(slave)], [], H, kernel=False)
        master.advance_to(150)
        assert dict(master.values) == threaded


def test_kernel_thread_switch(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SOFTHIL_KERNEL_THREAD", "0")
    assert not kernel_thread()
    monkeypatch.setenv("SOFTHIL_KERNEL_THREAD", "1")
    assert kernel_thread()
    monkeypatch.delenv("SOFTHIL_KERNEL_THREAD")
    assert kernel_thread() is None  # where it pays
    for value in ("yes", "2", ""):
        monkeypatch.setenv("SOFTHIL_KERNEL_THREAD", value)
        with pytest.raises(HilError, match=rf"^SOFTHIL_KERNEL_THREAD='{value}': must be 1 "):
            kernel_thread()


def test_closing_an_instance_the_worker_steps_waits_for_it(drive_cylinder_fmu: BuiltFmu) -> None:
    """A run that fails between starting the worker and waiting for it closes its FMUs while
    the worker may be stepping them: closing waits for the job and stops the thread."""
    slave = FmuSlave(drive_cylinder_fmu, "cylinder1")
    master = Algorithm([FmuParticipant(slave)], [], H, kernel=True)
    before = os_threads()
    assert master.start_advance(5000, 0.0)
    assert os_threads() == before + 1
    slave.close()
    assert os_threads() == before
    assert not slave.alive


@pytest.mark.parametrize(("min_cost", "starts"), [(1e-12, 100 - 12), (1e3, 0)])
def test_unset_the_switch_times_the_first_periods_and_uses_the_thread_where_it_pays(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, min_cost: float, starts: int
) -> None:
    """SOFTHIL_KERNEL_THREAD unset: the first OVERLAP_PROBES periods are stepped in turn and
    timed; a rig whose median period costs at least the threshold goes on on the thread (every
    later period started there), one that costs less stays in turn. Files as in turn."""
    from hil.cosim import execution

    assert execution.OVERLAP_PROBES == 12
    monkeypatch.delenv("SOFTHIL_KERNEL_THREAD", raising=False)
    monkeypatch.setattr("hil.run.OVERLAP_MIN_COST", min_cost)
    monkeypatch.setattr("hil.run.two_cores", lambda: True)
    calls = []
    real = Algorithm.start_advance

    def spy(self: Algorithm, tick: int, spin: float = 0.0) -> bool:
        calls.append(tick)
        return real(self, tick, spin)

    monkeypatch.setattr(Algorithm, "start_advance", spy)
    scenario = load_scenario()
    scenario = replace(scenario, duration=1.0, robot=replace(scenario.robot, segments=2), seed=3)
    run_scenario(
        scenario, RunOptions(out=tmp_path / "auto", inprocess=True, progress=False, reports=False)
    )
    assert len(calls) == starts
    if starts:
        assert calls[0] == 13 * scenario.control_ticks  # after SYNC 12: the probes are done
    monkeypatch.setenv("SOFTHIL_KERNEL_THREAD", "0")
    run_scenario(
        scenario, RunOptions(out=tmp_path / "turn", inprocess=True, progress=False, reports=False)
    )
    for name in ("can.log", "signals.csv"):
        assert (tmp_path / "auto" / name).read_bytes() == (tmp_path / "turn" / name).read_bytes()


def test_kernel_seconds_count_the_kernels_stepping_only(drive_cylinder_fmu: BuiltFmu) -> None:
    """What an in-process run times in its first periods to choose the thread: the kernel's
    stepping (what the thread would take over), not a Python participant's step (the camera
    steps in Python either way; counting it sent a 1-segment arm onto the thread)."""

    class Slow(Sampler):
        def step(self, time: float, step: float) -> None:
            super().step(time, step)
            pause = perf_counter() + 0.005  # 5 ms of Python work at every step
            while perf_counter() < pause:
                pass

    with FmuSlave(drive_cylinder_fmu, "cylinder2") as slave:
        slow = Slow()
        slow.decimation = 5
        master = Algorithm(
            [FmuParticipant(slave), slow], [Connection("cylinder2.x", "sampler.x")], H, kernel=True
        )
        started = perf_counter()
        master.advance_to(20)
        wall = perf_counter() - started
        assert len(slow.received) == 4
        assert 0.0 < master.kernel_seconds < 0.005 < wall - master.kernel_seconds
    with FmuSlave(drive_cylinder_fmu, "cylinder3") as slave:
        python = Algorithm([FmuParticipant(slave)], [], H, kernel=False)
        python.advance_to(25)
        assert python.kernel_seconds == 0.0


@pytest.mark.parametrize(("min_cost", "on_thread"), [(60e-6, False), (30e-6, True)])
def test_the_run_chooses_the_thread_by_the_kernels_stepping_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, min_cost: float, on_thread: bool
) -> None:
    """The first 12 periods timed by the master's kernel clock, here a fake one that gives each
    kernel call 20 us (two a period: the camera splits it): 40 us a period stays in turn
    against a threshold of 60 us and takes the thread against 30 us."""

    class Clock:
        now = 0.0

        def perf_counter(self) -> float:
            self.now += 20e-6  # read before and after a kernel call: 20 us each
            return self.now

    monkeypatch.delenv("SOFTHIL_KERNEL_THREAD", raising=False)
    monkeypatch.setattr("hil.cosim.algorithm.time", Clock())
    monkeypatch.setattr("hil.run.OVERLAP_MIN_COST", min_cost)
    monkeypatch.setattr("hil.run.two_cores", lambda: True)
    scenario = replace(load_scenario(), duration=0.3, seed=3)
    result = run_scenario(scenario, RunOptions(out=tmp_path, inprocess=True, progress=False))
    assert result.summary["periods_on_kernel_thread"] == (30 - 12 if on_thread else 0)


@pytest.mark.parametrize("decimation", [4, 1])
def test_the_worker_keeps_each_instances_time_as_stepping_in_turn(
    drive_cylinder_fmu: BuiltFmu, decimation: int
) -> None:
    """FmuSlave.time after a period on the worker thread, or stepped in turn by the kernel, is
    the one FmuSlave.do_step leaves in the Python master, bit for bit: the end of the last step
    taken, decimation included."""
    times = []
    for ahead, kernel in ((True, True), (False, True), (False, False)):
        with FmuSlave(drive_cylinder_fmu, "a") as a, FmuSlave(drive_cylinder_fmu, "b") as b:
            master = Algorithm(
                [FmuParticipant(a), FmuParticipant(b, decimation)], [], H, kernel=kernel
            )
            for tick in (7, 10):
                if ahead:
                    assert master.start_advance(tick, 0.0)
                master.advance_to(tick)
                times.append((ahead, kernel, tick, a.time, b.time))
            master.settle()
    assert [t[2:] for t in times[:2]] == [t[2:] for t in times[2:4]] == [t[2:] for t in times[4:]]
    last = -(-10 // decimation) * decimation
    assert times[-1][3:] == pytest.approx((10 * H, last * H))
