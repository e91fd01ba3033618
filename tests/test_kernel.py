"""Tests for the stepping kernel (hil/kernel): the C inner loop against the Python master.

The Python master is the reference. The same coupled system (two segments of DriveCylinder and
FeaSegment, one FMU at decimation 2, a connection with gain and offset, a Python probe stepping at
decimation 10 between two FMUs, a device node whose outputs change only when published at SYNC)
runs once per path; every value must be bit-identical at every comparison point.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path

import pytest

from hil.errors import FmuError, HilError
from hil.fmu.build import BuiltFmu
from hil.fmu.slave import FmuSlave
from hil.master import Connection, FmuParticipant, Master
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


def coupled(
    cylinder: BuiltFmu, segment: BuiltFmu, kernel: bool
) -> tuple[Master, Probe, Firmware, list[FmuSlave]]:
    slaves = []
    participants: list = []
    for n in (1, 2):
        c = FmuSlave(cylinder, f"cylinder{n}")
        s = FmuSlave(segment, f"segment{n}")
        slaves += [c, s]
        participants += [FmuParticipant(c), FmuParticipant(s, decimation=2 if n == 1 else 1)]
    probe, firmware = Probe(), Firmware()
    participants += [probe, firmware]
    connections = [
        Connection("drive.x_ref", "cylinder1.x_ref"),
        Connection("cylinder1.x", "drive.x"),
        Connection("cylinder1.x", "probe.x"),
        Connection("probe.x_ref", "cylinder2.x_ref"),
        # a gain and an offset on a pressure: the order of the two roundings is tested
        Connection("segment1.p_b", "cylinder1.p_b", gain=0.9, offset=137.5),
    ]
    for n in (1, 2):
        connections += [
            Connection(f"cylinder{n}.x", f"segment{n}.x_piston"),
            Connection(f"segment{n}.p_a", f"cylinder{n}.p_a"),
        ]
    connections.append(Connection("segment2.p_b", "cylinder2.p_b"))
    master = Master(participants, connections, H, kernel=kernel)
    master.set_input("segment2", "tau_ext", 0.002)
    return master, probe, firmware, slaves


def run_syncs(
    cylinder: BuiltFmu,
    segment: BuiltFmu,
    kernel: bool,
    syncs: int,
    advance: Callable[[Master, int], None] | None = None,
) -> tuple[list[dict[str, float]], Probe, bool]:
    master, probe, firmware, slaves = coupled(cylinder, segment, kernel)
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
        used = master.uses_kernel
    finally:
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
    # the comparison means something: the pistons and pressures moved
    for key in ("cylinder1.x", "cylinder2.x", "segment1.p_b", "segment2.kappa"):
        assert len({row[key] for row in python}) > 20, key
    assert [t for t, _ in python_probe.received] == [k * H for k in range(0, 600, 10)]


def test_kernel_and_python_master_are_bit_identical_at_every_tick(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu
) -> None:
    ticks: dict[bool, list[dict[str, float]]] = {False: [], True: []}

    def tick_by_tick(master: Master, target: int) -> None:
        while master.tick < target:
            master.advance_to(master.tick + 1)
            ticks[master.uses_kernel].append(dict(master.values))

    python, _, _ = run_syncs(drive_cylinder_fmu, fea_segment_fmu, False, 12, tick_by_tick)
    kernel, _, _ = run_syncs(drive_cylinder_fmu, fea_segment_fmu, True, 12, tick_by_tick)
    assert len(ticks[True]) == 120
    assert ticks[True] == ticks[False]
    assert kernel == python


def test_switching_to_python_for_an_observer_and_back_keeps_identity(
    drive_cylinder_fmu: BuiltFmu, fea_segment_fmu: BuiltFmu
) -> None:
    class Recorder:
        def __init__(self) -> None:
            self.calls: list[tuple[int, dict[str, float]]] = []

        def observe(self, tick: int, values: Mapping[str, float]) -> None:
            self.calls.append((tick, dict(values)))

    def observed(master: Master, target: int) -> None:
        # the periods ending at SYNC 2 and 33 run with an observer (every tick in Python), the
        # others in C. The firmware's setpoint is 0.025 in both Python periods and 0.03 in the C
        # period just before the second, so the kernel must hand back what it last sent, or the
        # Python path would skip setting 0.025 again and the cylinder would keep 0.03.
        recorder = recorders[master.uses_kernel]
        if target in (20, 330):
            master.add_observer(recorder)
        master.advance_to(target)
        master.observers.clear()

    recorders = {False: Recorder(), True: Recorder()}
    python, _, _ = run_syncs(drive_cylinder_fmu, fea_segment_fmu, False, 40, observed)
    kernel, _, used = run_syncs(drive_cylinder_fmu, fea_segment_fmu, True, 40, observed)
    assert used
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
        assert Master(participants, [], H).uses_kernel
        assert not Master(participants, [], H, kernel=False).uses_kernel
        monkeypatch.setenv("SOFTHIL_KERNEL", "0")
        master = Master(participants, [], H)
        assert not master.uses_kernel
        master.advance_to(3)
        assert master.tick == 3
        monkeypatch.setenv("SOFTHIL_KERNEL", "1")
        assert Master(participants, [], H).uses_kernel
        for value in ("yes", "off", "2", ""):  # a misspelt switch is not silently "on"
            monkeypatch.setenv("SOFTHIL_KERNEL", value)
            with pytest.raises(HilError, match=rf"^SOFTHIL_KERNEL='{value}': must be 1 .* or 0"):
                Master(participants, [], H)


def test_master_without_fmus_does_not_use_the_kernel() -> None:
    assert not Master([Probe()], [], H, kernel=True).uses_kernel


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
    master = Master([FmuParticipant(slave)], [], H, kernel=True)
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
    for flag in ("0", "1"):
        monkeypatch.setenv("SOFTHIL_KERNEL", flag)
        out = tmp_path / flag
        run_scenario(scenario, RunOptions(out=out, inprocess=True, progress=False))
        files[flag] = {name: (out / name).read_bytes() for name in ("can.log", "signals.csv")}
    assert files["1"] == files["0"]
    assert len(files["1"]["signals.csv"].splitlines()) > 90
