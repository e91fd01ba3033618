"""The plant node: the simulated rig answering the controller's SYNC (ARCHITECTURE.md).

On SYNC(c) the plant
  1. advances the physics to t_c = c T with the commands that were active,
  2. latches the commands received since the previous SYNC (they act from this SYNC on),
     applying the drives' own safety (over-pressure: EMCY and hold; command timeout: EMCY and
     hold) as their firmware would,
  3. sends the camera marker frames that became available in the period (each with its exposure
     time), then every drive's status frame echoing c. Status frames go last so that, on an
     ordered bus, the last of them tells the controller the cycle is complete.
Everything the plant sends or receives is logged with simulation time; signals are recorded at
every SYNC. Nothing here depends on wall-clock time except the wait for a silent peer.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import can
import numpy as np

from controllers import kinematics
from controllers.protocol import (
    COUNTER_MODULO,
    EMCY_COMMAND_TIMEOUT,
    EMCY_OVER_PRESSURE,
    NMT_OPERATIONAL,
    CameraMarker,
    ControllerState,
    DriveCommand,
    DriveStatus,
    Emcy,
    Frame,
    FrameError,
    Heartbeat,
    Protocol,
    Sync,
)
from controllers.trajectories import CurvatureProfile
from hil.errors import BusError, FmuError, ProtocolError
from hil.fmu.slave import FmuSlave
from hil.master import Connection, FmuParticipant, Master
from hil.recording import CanLogger, SignalRecorder
from hil.scenario import Scenario

FAULT_OVER_PRESSURE = 16  # plant-side fault bits, above the DriveCylinder's own 1, 2, 4
FAULT_COMMAND_TIMEOUT = 32
PRESSURE_RANGE = (-327680.0, 327670.0)  # DriveStatus.p_a/p_b in the DBC [Pa]
POSITION_RANGE = (0.0, 0.13107)  # DriveStatus.piston_position [m]
HEARTBEAT_PERIOD = 1.0  # [s]


def build_planar_arm(scenario: Scenario) -> tuple[list[FmuParticipant], list[Connection]]:
    """FMU participants and connections of a planar arm: drive n moves segment n's piston, the
    segment's chamber pressures load the drive. Scenario connections replace defaults that drive
    the same input, and add the others."""
    robot = scenario.robot
    participants: list[FmuParticipant] = []
    connections: dict[str, Connection] = {}
    try:
        for n in range(1, robot.segments + 1):
            cylinder = FmuSlave(
                _fmu_ref(scenario, robot.cylinder_fmu), f"cylinder{n}", robot.cylinder
            )
            participants.append(FmuParticipant(cylinder, robot.cylinder_decimation))
            segment = FmuSlave(
                _fmu_ref(scenario, robot.segment_fmu),
                f"segment{n}",
                {**_shared_geometry(robot.cylinder), **robot.segment},
            )
            participants.append(FmuParticipant(segment, robot.segment_decimation))
            for source, target in (
                (f"cylinder{n}.x", f"segment{n}.x_piston"),
                (f"segment{n}.p_a", f"cylinder{n}.p_a"),
                (f"segment{n}.p_b", f"cylinder{n}.p_b"),
            ):
                connections[target] = Connection(source, target)
    except BaseException:
        for participant in participants:
            participant.close()
        raise
    for c in scenario.connections:
        connections[c.target] = Connection(c.source, c.target, c.gain, c.offset)
    return participants, list(connections.values())


def _fmu_ref(scenario: Scenario, fmu: str) -> str:
    if fmu.endswith(".fmu"):
        from pathlib import Path

        path = Path(fmu)
        return str(path if path.is_absolute() else Path(scenario.source).parent / path)
    return fmu


def _shared_geometry(cylinder: dict[str, float]) -> dict[str, float]:
    """The segment's gas circuit includes the cylinder: bore and stroke must agree, and the
    circuit is sealed where the piston starts."""
    shared: dict[str, float] = {k: cylinder[k] for k in ("bore", "stroke") if k in cylinder}
    if "x_start" in cylinder:
        shared["x_seal"] = cylinder["x_start"]
    return shared


class CameraNode:
    """The camera: exposes at its rate, sees the true shape (PCC from the true curvatures) and
    delivers each frame `latency` later, with optional Gaussian marker noise."""

    def __init__(self, scenario: Scenario, lengths: list[float], rng: np.random.Generator) -> None:
        self.period_ticks = scenario.camera_ticks
        self.latency_ticks = scenario.latency_ticks
        self.noise = scenario.camera.noise
        self.step = scenario.timing.step
        self.base = scenario.robot.base
        self.lengths = lengths
        self.segments = len(lengths)
        self.rng = rng
        self.frame_index = 0
        self.queue: deque[tuple[int, int, int, np.ndarray]] = deque()

    def observe(self, tick: int, values: Mapping[str, float]) -> None:
        if tick % self.period_ticks:
            return
        kappas = [values[f"segment{n}.kappa"] for n in range(1, self.segments + 1)]
        points = kinematics.markers(kappas, self.lengths, self.base)
        if self.noise > 0.0:
            points = points + self.rng.normal(0.0, self.noise, points.shape)
        self.queue.append((tick + self.latency_ticks, tick, self.frame_index, points))
        self.frame_index += 1

    def frames_due(self, sync_tick: int) -> list[CameraMarker]:
        """Marker frames of every exposure available by `sync_tick`, oldest first."""
        frames = []
        while self.queue and self.queue[0][0] <= sync_tick:
            _, exposure, index, points = self.queue.popleft()
            offset = (sync_tick - exposure) * self.step
            for m, (x, y) in enumerate(points):
                frames.append(CameraMarker(m, float(x), float(y), index, offset))
        return frames


@dataclass
class DriveNode:
    """Drive n's firmware on the bus: latches commands at SYNC and guards its own safety."""

    node: int
    x_start: float
    x_seal: float
    max_pressure: float
    timeout_ticks: int
    active_setpoint: float = 0.0
    active_enable: bool = True
    pending: DriveCommand | None = None
    last_command_tick: int = 0
    timed_out: bool = False
    over_pressure: bool = False
    hold_position: float = 0.0
    missed: int = 0
    stale: int = 0
    emcy: list[Emcy] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.active_setpoint = self.x_start

    def receive(self, command: DriveCommand) -> None:
        self.pending = command

    def latch(self, sync_tick: int, counter: int, x: float, p_a: float, p_b: float) -> float:
        """Apply the commands of the last period at this SYNC; returns the servo setpoint."""
        expected = (counter - 1) % COUNTER_MODULO
        if self.pending is not None and self.pending.counter == expected:
            self.active_setpoint = self.pending.piston_setpoint
            self.active_enable = self.pending.enable
            self.last_command_tick = sync_tick
            self.timed_out = False
        elif self.pending is not None:
            self.stale += 1
        elif sync_tick > 0:
            self.missed += 1
        self.pending = None
        if not self.timed_out and sync_tick - self.last_command_tick > self.timeout_ticks:
            self.timed_out = True
            self.hold_position = x
            self.emcy.append(Emcy(self.node, EMCY_COMMAND_TIMEOUT, 1, max(p_a, p_b), counter))
        pressure = max(abs(p_a), abs(p_b))
        if not self.over_pressure and pressure > self.max_pressure:
            self.over_pressure = True
            self.emcy.append(
                Emcy(self.node, EMCY_OVER_PRESSURE, 1, _clamp(pressure, *PRESSURE_RANGE), counter)
            )
        elif self.over_pressure and pressure < 0.9 * self.max_pressure:
            self.over_pressure = False
        setpoint = self.hold_position if self.timed_out else self.active_setpoint
        if self.over_pressure and (setpoint - x) * (self.x_seal - x) <= 0.0:
            setpoint = x  # hold: only moves back towards the sealing position relieve pressure
        return setpoint

    @property
    def fault_bits(self) -> int:
        return (FAULT_OVER_PRESSURE if self.over_pressure else 0) | (
            FAULT_COMMAND_TIMEOUT if self.timed_out else 0
        )


@dataclass
class PlantStats:
    sync_received: int = 0
    commands_missed: int = 0
    commands_stale: int = 0
    unknown_frames: int = 0
    emcy_sent: int = 0
    wall_time: float = 0.0


class Plant:
    """The simulated rig on the bus; `run` serves SYNCs until the scenario's last cycle."""

    def __init__(
        self,
        scenario: Scenario,
        bus: can.BusABC,
        master: Master,
        signals: SignalRecorder,
        can_log: CanLogger,
        protocol: Protocol | None = None,
    ) -> None:
        self.scenario = scenario
        self.bus = bus
        self.master = master
        self.signals = signals
        self.can_log = can_log
        self.protocol = protocol or Protocol()
        self.stats = PlantStats()
        robot = scenario.robot
        self.n = robot.segments
        cylinder = robot.cylinder
        x_start = float(cylinder.get("x_start", 0.025))
        self.lengths = [float(robot.segment.get("length", 0.06))] * self.n
        self.drives = [
            DriveNode(
                n,
                x_start,
                x_start,
                scenario.safety.max_pressure,
                round(scenario.safety.command_timeout / scenario.timing.step),
            )
            for n in range(1, self.n + 1)
        ]
        self.camera = CameraNode(scenario, self.lengths, np.random.default_rng(scenario.seed))
        master.add_observer(self.camera)
        t = scenario.task
        self.profile = CurvatureProfile(
            steps=t.steps, sine=None if t.sine is None else _sine(t.sine), scale=t.scale
        )
        self.x_refs = [x_start] * self.n
        self.sim_time = 0.0
        self.cycle = -1
        self.heartbeat_every = max(1, round(HEARTBEAT_PERIOD / scenario.timing.control_period))

    def run(
        self, peer_alive: Callable[[], str | None], progress: Callable[[int], None] | None = None
    ) -> PlantStats:
        """Serve SYNC(0..cycles). `peer_alive` returns None while the controller lives, else why
        it is gone; a silent bus is checked against it and against the controller timeout."""
        started = time.perf_counter()
        last_heard = time.monotonic()
        final = self.scenario.cycles
        try:
            while self.cycle < final:
                message = self.bus.recv(timeout=0.1)
                if message is None:
                    gone = peer_alive()
                    if gone is not None:
                        raise ProtocolError(
                            f"{gone} at t = {self.sim_time:.3f} s (after SYNC {self.cycle}); "
                            "the plant stopped"
                        )
                    if time.monotonic() - last_heard > self.scenario.controller.timeout:
                        raise ProtocolError(
                            f"no frame from the controller for {self.scenario.controller.timeout:g}"
                            f" s at t = {self.sim_time:.3f} s (after SYNC {self.cycle})"
                        )
                    continue
                last_heard = time.monotonic()
                self._handle(message, progress)
        finally:
            self.stats.wall_time = time.perf_counter() - started
            self.signals.end_row()
            self.can_log.flush()
        return self.stats

    def _decode(self, message: can.Message) -> Frame | None:
        try:
            return self.protocol.decode(message)
        except FrameError as exc:
            self.can_log.log(message, self.sim_time, received=True)
            if self.scenario.controller.policy == "strict":
                raise BusError(f"at t = {self.sim_time:.3f} s: {exc}") from exc
            self.stats.unknown_frames += 1
            return None

    def _handle(self, message: can.Message, progress: Callable[[int], None] | None) -> None:
        frame = self._decode(message)
        if frame is None:
            return
        if isinstance(frame, Sync):
            expected = (self.cycle + 1) % COUNTER_MODULO
            if frame.counter != expected:
                raise ProtocolError(
                    f"SYNC counter {frame.counter} where {expected} was due "
                    f"(t = {self.sim_time:.3f} s): a SYNC was lost or another master is on the bus"
                )
            self.cycle += 1
            self.sim_time = self.cycle * self.scenario.timing.control_period
            self.can_log.log(message, self.sim_time, received=True)
            self.stats.sync_received += 1
            self._on_sync(self.cycle)
            if progress is not None:
                progress(self.cycle)
            return
        self.can_log.log(message, self.sim_time, received=True)
        if isinstance(frame, DriveCommand) and 1 <= frame.node <= self.n:
            self.drives[frame.node - 1].receive(frame)
        elif isinstance(frame, ControllerState) and 1 <= frame.node <= self.n:
            self.signals.controller_state(frame.node, frame.kappa_ref, frame.kappa_est)
        elif self.scenario.controller.policy == "strict":
            raise BusError(
                f"at t = {self.sim_time:.3f} s: unexpected {type(frame).__name__} frame "
                f"0x{message.arbitration_id:03X} on the plant's bus"
            )
        else:
            self.stats.unknown_frames += 1

    def _send(self, frame: Frame) -> None:
        message = self.protocol.encode(frame, timestamp=self.sim_time)
        try:
            self.bus.send(message)
        except (can.CanError, OSError) as exc:
            raise BusError(f"sending 0x{message.arbitration_id:03X}: {exc}") from exc
        self.can_log.log(message, self.sim_time, received=False)

    def _on_sync(self, cycle: int) -> None:
        sync_tick = cycle * self.scenario.control_ticks
        try:
            self.master.advance_to(sync_tick)
        except FmuError as exc:
            raise FmuError(f"at t = {self.sim_time:.3f} s: {exc}") from exc
        values = self.master.values
        emcy: list[Emcy] = []
        for drive in self.drives:
            n = drive.node
            x = values[f"cylinder{n}.x"]
            p_a, p_b = values[f"segment{n}.p_a"], values[f"segment{n}.p_b"]
            setpoint = drive.latch(sync_tick, cycle, x, p_a, p_b)
            self.x_refs[n - 1] = setpoint
            self.master.set_input(f"cylinder{n}", "x_ref", setpoint)
            self.master.set_input(f"cylinder{n}", "enable", 1.0 if drive.active_enable else 0.0)
            emcy += drive.emcy
            drive.emcy.clear()
        self._record(cycle)
        for frame in emcy:
            self._send(frame)
            self.stats.emcy_sent += 1
        if cycle % self.heartbeat_every == 0:
            for drive in self.drives:
                self._send(Heartbeat(drive.node, NMT_OPERATIONAL))
        for marker in self.camera.frames_due(sync_tick):
            self._send(marker)
        for drive in self.drives:
            n = drive.node
            self._send(
                DriveStatus(
                    n,
                    _clamp(values[f"cylinder{n}.x"], *POSITION_RANGE),
                    _clamp(values[f"segment{n}.p_a"], *PRESSURE_RANGE),
                    _clamp(values[f"segment{n}.p_b"], *PRESSURE_RANGE),
                    (int(values[f"cylinder{n}.fault"]) | drive.fault_bits) & 0xFF,
                    cycle,
                )
            )
        self.stats.commands_missed = sum(d.missed for d in self.drives)
        self.stats.commands_stale = sum(d.stale for d in self.drives)
        self.can_log.flush()

    def _record(self, cycle: int) -> None:
        values = self.master.values
        row: dict[str, float] = {}
        for n in range(1, self.n + 1):
            row[f"kappa_ref_{n}"] = self.profile.for_segment(n - 1, self.sim_time)
            row[f"kappa_{n}"] = values[f"segment{n}.kappa"]
            row[f"theta_{n}"] = values[f"segment{n}.theta"]
            row[f"p_a_{n}"] = values[f"segment{n}.p_a"]
            row[f"p_b_{n}"] = values[f"segment{n}.p_b"]
            row[f"x_{n}"] = values[f"cylinder{n}.x"]
            row[f"x_ref_{n}"] = self.x_refs[n - 1]
            row[f"v_{n}"] = values[f"cylinder{n}.v"]
            row[f"i_motor_{n}"] = values[f"cylinder{n}.i_motor"]
            row[f"fault_{n}"] = float(
                int(values[f"cylinder{n}.fault"]) | self.drives[n - 1].fault_bits
            )
        self.signals.begin_row(self.sim_time, row)


def _clamp(value: float, lo: float, hi: float) -> float:
    return lo if value < lo else hi if value > hi else (value if math.isfinite(value) else 0.0)


def _sine(spec):  # noqa: ANN001, ANN202 - SineSpec -> Sine
    from controllers.trajectories import Sine

    return Sine(spec.start, spec.amplitude, spec.frequency, spec.offset)
