"""The golden CAN log and its replay harness.

`default.log` is the CAN log of the default scenario cut to 2 s (the sine starts at the end),
run in-process, exactly as the plant wrote it: SYNC, DriveCommand and ControllerState frames it
received (R), everything it sent (T), stamped with the default start instant plus simulation
time. `replay` feeds a fresh Plant only the received frames, in the logged order, on a python-can
virtual bus, and returns the log the plant writes; the test requires it to equal the golden file
byte for byte.

Beside it, `PLANT_GOLDENS` hold the same kind of log for robots with other FMUs (the soft fish;
the planar arm with gripper, table and objects in the Environment FMU), cut short: replayed the
same way, they pin the plant's models to the bit, so that a change meant to keep the results
(an FMU made faster) is checked to keep them. Their controller side is replayed as the default
log's is (hil.replay, tests/test_golden_log.py): the fish's and the gripper arm's own
controllers, fed the plant's frames, must send the controller's frames of the log.

The golden files change only on purpose, never in a test run:

    python -m tests.golden --regenerate    # then review the diff of tests/golden/*.log
"""

from __future__ import annotations

import tempfile
import uuid
from pathlib import Path

import can

from hil.devices import HEARTBEAT_PERIOD
from hil.plant import Plant
from hil.recording import CanLogger, SignalRecorder
from hil.rig import build_rig
from hil.run import RunOptions, run_scenario
from hil.scenario import DEFAULT_SCENARIO, Scenario, load_scenario, log_start
from rigbus.canbus import BusSpec, open_bus
from rigbus.protocol import Protocol

ROBOTS = Path(__file__).resolve().parents[2] / "robots"
DEFAULT_LOG = ROBOTS / "planar_arm" / "golden" / "default.log"
# the same run in the other formats CAN tools exchange, for the controller replay tests
FORMATS = (".log", ".asc", ".blf")
DURATION = 2.0  # [s] of the default scenario: the first step and most of its hold
# name: (robot kind, seconds kept); the scenarios are robots/<kind>/scenarios/<name>.toml, their
# logs robots/<kind>/golden/<name>.log
PLANT_GOLDENS = {
    "fish-escape": ("fish", 0.4),
    "planar-grasp": ("planar_arm", 1.5),
}


def plant_golden(name: str) -> Path:
    return ROBOTS / PLANT_GOLDENS[name][0] / "golden" / f"{name}.log"


def write_plant_scenario(name: str, folder: Path) -> Path:
    """Scenario `name` of PLANT_GOLDENS cut to its seconds, written to folder/<name>.toml."""
    kind, seconds = PLANT_GOLDENS[name]
    lines = (ROBOTS / kind / "scenarios" / f"{name}.toml").read_text().splitlines()
    if not any(line.startswith("duration = ") for line in lines):
        raise RuntimeError(f"{name}.toml no longer has a duration line: update tests/golden")
    lines = [f"duration = {seconds}" if line.startswith("duration = ") else line for line in lines]
    path = folder / f"{name}.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def write_scenario(folder: Path) -> Path:
    """The default scenario cut to DURATION, written to folder/golden.toml."""
    text = DEFAULT_SCENARIO.read_text()
    for old, new in (
        ("duration = 10.0", f"duration = {DURATION}"),
        ("sine = { start = 7.0", f"sine = {{ start = {DURATION}"),
    ):
        if old not in text:
            raise RuntimeError(f"the default scenario no longer has {old!r}: update tests/golden")
        text = text.replace(old, new)
    path = folder / "golden.toml"
    path.write_text(text)
    return path


def run_default(folder: Path, can_log: str = "can.log") -> Path:
    """Run the shortened default scenario in-process into folder/run; its CAN log."""
    scenario = load_scenario(write_scenario(folder))
    result = run_scenario(
        scenario,
        RunOptions(
            out=folder / f"run{Path(can_log).suffix}",
            inprocess=True,
            progress=False,
            can_log=can_log,
        ),
    )
    return result.out / can_log


def received_frames(log: Path) -> list[can.Message]:
    """The frames the plant received (R lines), in the logged order."""
    return [message for message in can.LogReader(str(log)) if message.is_rx]


def replay(log: Path, scenario: Scenario, folder: Path) -> Path:
    """Feed a fresh plant the received frames of `log`; the CAN log it writes (folder/can.log).

    Every frame is queued on the virtual bus before the plant starts: the plant handles them in
    order, so commands answer the SYNC before them as they did in the run, with no controller and
    no waiting."""
    channel = f"golden-{uuid.uuid4().hex[:8]}"
    feeder, plant_bus = open_bus(BusSpec("virtual", channel)), open_bus(BusSpec("virtual", channel))
    rig = build_rig(scenario)
    signals = SignalRecorder(folder / "signals.csv", rig.signals)
    out = folder / "can.log"
    can_log = CanLogger(out, start=log_start(scenario))
    heartbeat_every = max(1, round(HEARTBEAT_PERIOD / scenario.timing.control_period))
    plant = Plant(scenario, plant_bus, rig, signals, can_log, Protocol(), heartbeat_every)
    try:
        for message in received_frames(log):
            feeder.send(message)
        plant.run(lambda: "the golden log has no more frames")
    finally:
        signals.close()
        can_log.close()
        rig.close()
        feeder.shutdown()
        plant_bus.shutdown()
    return out


def regenerate() -> list[Path]:
    """Rewrite default.log, default.asc and default.blf and the PLANT_GOLDENS from fresh
    in-process runs; the files written."""
    written = []
    with tempfile.TemporaryDirectory() as tmp:
        for suffix in FORMATS:
            log = run_default(Path(tmp), f"can{suffix}")
            DEFAULT_LOG.with_suffix(suffix).write_bytes(log.read_bytes())
            written.append(DEFAULT_LOG.with_suffix(suffix))
        for name in PLANT_GOLDENS:
            scenario = load_scenario(write_plant_scenario(name, Path(tmp)))
            result = run_scenario(
                scenario, RunOptions(out=Path(tmp) / name, inprocess=True, progress=False)
            )
            plant_golden(name).write_bytes((result.out / "can.log").read_bytes())
            written.append(plant_golden(name))
    return written
