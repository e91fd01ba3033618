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
from controllers.canbus import connection_closed
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
from hil.errors import BusError, FmuError, ProtocolError
from hil.fmu.slave import FmuSlave
from hil.master import Connection, FmuParticipant, Master, Participant
from hil.recording import CanLogger, SignalRecorder
from hil.scenario import Scenario, fmu_interface, fmu_path, robot_value

FAULT_OVER_PRESSURE = 16  # plant-side fault bits, above the DriveCylinder's own 1, 2, 4
FAULT_COMMAND_TIMEOUT = 32
HEARTBEAT_PERIOD = 1.0  # [s]


@dataclass
class Rig:
    """Everything the master steps: FMUs, drive firmware nodes and the camera, and their wiring."""

    participants: list[Participant]
    connections: list[Connection]
    drives: list[DriveNode]
    camera: CameraNode

    def close(self) -> None:
        for participant in self.participants:
            if isinstance(participant, FmuParticipant):
                participant.close()


def build_planar_arm(scenario: Scenario) -> Rig:
    """The planar arm as participants and connections. For each n: drive n's firmware sets
    cylinder n's setpoint and watches its position and segment n's pressures; cylinder n moves
    segment n's piston and feels its pressures; the camera sees every segment's curvature.
    Scenario connections replace defaults that drive the same input, and add the others."""
    robot = scenario.robot
    fmus: list[FmuParticipant] = []
    connections: dict[str, Connection] = {}
    x_start = robot_value(scenario, "cylinder", "x_start")
    segment_parameters = fmu_interface(scenario.source, "robot.segment_fmu", robot.segment_fmu)
    # the segment's gas circuit includes the cylinder: same bore and stroke, sealed where the
    # piston starts
    geometry = {
        "bore": robot_value(scenario, "cylinder", "bore"),
        "stroke": robot_value(scenario, "cylinder", "stroke"),
        "x_seal": x_start,
    }
    geometry = {k: v for k, v in geometry.items() if k in segment_parameters}
    timeout_ticks = round(scenario.safety.command_timeout / scenario.timing.step)
    pressure_range = Protocol().signal_range("EMCY1", "pressure")
    drives = [
        DriveNode(
            n,
            x_start,
            x_start,
            scenario.safety.max_pressure,
            timeout_ticks,
            pressure_range=pressure_range,
        )
        for n in range(1, robot.segments + 1)
    ]
    lengths = [robot_value(scenario, "segment", "length")] * robot.segments
    camera = CameraNode(scenario, lengths, np.random.default_rng(scenario.seed))
    try:
        for n in range(1, robot.segments + 1):
            cylinder = FmuSlave(
                _fmu_ref(scenario, robot.cylinder_fmu), f"cylinder{n}", robot.cylinder
            )
            fmus.append(FmuParticipant(cylinder, robot.cylinder_decimation))
            segment = FmuSlave(
                _fmu_ref(scenario, robot.segment_fmu),
                f"segment{n}",
                {**geometry, **robot.segment},
            )
            fmus.append(FmuParticipant(segment, robot.segment_decimation))
            for source, target in (
                (f"cylinder{n}.x", f"segment{n}.x_piston"),
                (f"segment{n}.p_a", f"cylinder{n}.p_a"),
                (f"segment{n}.p_b", f"cylinder{n}.p_b"),
                (f"drive{n}.x_ref", f"cylinder{n}.x_ref"),
                (f"drive{n}.enable", f"cylinder{n}.enable"),
                (f"cylinder{n}.x", f"drive{n}.x"),
                (f"segment{n}.p_a", f"drive{n}.p_a"),
                (f"segment{n}.p_b", f"drive{n}.p_b"),
                (f"cylinder{n}.fault", f"drive{n}.servo_fault"),
                (f"segment{n}.kappa", f"camera.kappa_{n}"),
            ):
                connections[target] = Connection(source, target)
    except BaseException:
        for participant in fmus:
            participant.close()
        raise
    for c in scenario.connections:
        connections[c.target] = Connection(c.source, c.target, c.gain, c.offset)
    participants: list[Participant] = [*fmus, *drives, camera]
    return Rig(participants, list(connections.values()), drives, camera)


def _fmu_ref(scenario: Scenario, fmu: str) -> str:
    return str(fmu_path(scenario.source, fmu)) if fmu.endswith(".fmu") else fmu


class CameraNode:
    """The camera as a participant: it exposes at its rate (its decimation), sees the true shape
    (PCC from the curvatures on its inputs) and delivers each frame `latency` later, with
    optional Gaussian marker noise."""

    name = "camera"

    def __init__(self, scenario: Scenario, lengths: list[float], rng: np.random.Generator) -> None:
        self.period_ticks = scenario.camera_ticks
        self.latency_ticks = scenario.latency_ticks
        self.noise = scenario.camera.noise
        self.macro_step = scenario.timing.step
        self.base = scenario.robot.base
        self.lengths = lengths
        self.segments = len(lengths)
        self.rng = rng
        self.decimation = self.period_ticks
        self.frame_index = 0
        self.queue: deque[tuple[int, int, int, np.ndarray]] = deque()
        self.kappas = [0.0] * self.segments

    def input_names(self) -> list[str]:
        return [f"kappa_{n}" for n in range(1, self.segments + 1)]

    def output_names(self) -> list[str]:
        return []

    def set_inputs(self, values: Mapping[str, float]) -> None:
        for name, value in values.items():
            self.kappas[int(name.rpartition("_")[2]) - 1] = value

    def get_outputs(self) -> dict[str, float]:
        return {}

    def step(self, time: float, step: float) -> None:
        """An exposure at `time` of the shape on the inputs (set from the state at `time`)."""
        tick = round(time / self.macro_step)
        kappas = self.kappas
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
            offset = (sync_tick - exposure) * self.macro_step
            for m, (x, y) in enumerate(points):
                frames.append(CameraMarker(m, float(x), float(y), index, offset))
        return frames


@dataclass
class DriveNode:
    """Drive n's firmware as a participant: between SYNCs it holds its outputs (the servo
    setpoint and enable); at SYNC it latches the last period's command and guards its own
    safety from its inputs (piston position, chamber pressures, the servo's fault bits)."""

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
    pressure_range: tuple[float, float] = (-math.inf, math.inf)  # EMCY.pressure in the DBC

    def __post_init__(self) -> None:
        self.active_setpoint = self.x_start
        self.setpoint = self.x_start
        self.name = f"drive{self.node}"
        self.decimation = 1
        self.servo_fault = 0

    def input_names(self) -> list[str]:
        return ["x", "p_a", "p_b", "servo_fault"]

    def output_names(self) -> list[str]:
        return ["x_ref", "enable", "fault"]

    def set_inputs(self, values: Mapping[str, float]) -> None:
        """Inputs are read at SYNC through `latch`; between SYNCs the firmware only holds."""

    def step(self, time: float, step: float) -> None:
        """Nothing happens between SYNCs: the outputs hold."""

    def get_outputs(self) -> dict[str, float]:
        return {
            "x_ref": self.setpoint,
            "enable": 1.0 if self.active_enable else 0.0,
            "fault": float((self.servo_fault | self.fault_bits) & 0xFF),
        }

    def receive(self, command: DriveCommand) -> None:
        self.pending = command

    def latch(self, sync_tick: int, counter: int, inputs: Mapping[str, float]) -> None:
        """Apply the commands of the last period at this SYNC, from the inputs at this SYNC."""
        x, p_a, p_b = inputs["x"], inputs["p_a"], inputs["p_b"]
        self.servo_fault = int(inputs["servo_fault"])
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
                Emcy(
                    self.node,
                    EMCY_OVER_PRESSURE,
                    1,
                    _clamp(pressure, *self.pressure_range),
                    counter,
                )
            )
        elif self.over_pressure and pressure < 0.9 * self.max_pressure:
            self.over_pressure = False
        setpoint = self.hold_position if self.timed_out else self.active_setpoint
        if self.over_pressure and (setpoint - x) * (self.x_seal - x) <= 0.0:
            setpoint = x  # hold: only moves back towards the sealing position relieve pressure
        self.setpoint = setpoint

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
        rig: Rig,
        signals: SignalRecorder,
        can_log: CanLogger,
        protocol: Protocol | None = None,
    ) -> None:
        self.scenario = scenario
        self.bus = bus
        self.master = Master(rig.participants, rig.connections, scenario.timing.step)
        self.signals = signals
        self.can_log = can_log
        self.protocol = protocol or Protocol()
        self.stats = PlantStats()
        self.n = scenario.robot.segments
        self.drives = rig.drives
        self.camera = rig.camera
        t = scenario.task
        self.profile = t.profile()
        # a sensor value beyond what its frame can carry is sent saturated, as an ADC would
        self.position_range = self.protocol.signal_range("DriveStatus1", "piston_position")
        self.pressure_range = self.protocol.signal_range("DriveStatus1", "p_a")
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
                    if connection_closed(self.bus):
                        raise BusError(
                            f"the loopback hub closed the bus at t = {self.sim_time:.3f} s"
                        )
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
            # t = c T from the integer cycle, rounded: files show 3.53, not 3.5300000000000002
            self.sim_time = round(self.cycle * self.scenario.timing.control_period, 9)
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
        try:
            message = self.protocol.encode(frame, timestamp=self.sim_time)
        except FrameError as exc:
            raise BusError(f"at t = {self.sim_time:.3f} s: {exc}") from exc
        try:
            self.bus.send(message)
        except (can.CanError, OSError) as exc:
            raise BusError(f"sending 0x{message.arbitration_id:03X}: {exc}") from exc
        self.can_log.log(message, self.sim_time, received=False)

    def _on_sync(self, cycle: int) -> None:
        sync_tick = cycle * self.scenario.control_ticks
        master = self.master
        try:
            master.advance_to(sync_tick)
        except FmuError as exc:
            raise FmuError(f"at t = {self.sim_time:.3f} s: {exc}") from exc
        emcy: list[Emcy] = []
        for drive in self.drives:
            drive.latch(sync_tick, cycle, master.inputs_of(drive.name))
            master.publish(drive.name)
            emcy += drive.emcy
            drive.emcy.clear()
        self._record()
        for frame in emcy:
            self._send(frame)
            self.stats.emcy_sent += 1
        if cycle % self.heartbeat_every == 0:
            for drive in self.drives:
                self._send(Heartbeat(drive.node, NMT_OPERATIONAL))
        for marker in self.camera.frames_due(sync_tick):
            self._send(marker)
        for drive in self.drives:
            seen = master.inputs_of(drive.name)  # what the firmware measures
            self._send(
                DriveStatus(
                    drive.node,
                    _clamp(seen["x"], *self.position_range),
                    _clamp(seen["p_a"], *self.pressure_range),
                    _clamp(seen["p_b"], *self.pressure_range),
                    int(master.values[f"{drive.name}.fault"]),
                    cycle,
                )
            )
        self.stats.commands_missed = sum(d.missed for d in self.drives)
        self.stats.commands_stale = sum(d.stale for d in self.drives)
        self.can_log.flush()

    def _record(self) -> None:
        values = self.master.values
        row: dict[str, float] = {}
        for n in range(1, self.n + 1):
            row[f"kappa_ref_{n}"] = self.profile.for_segment(n - 1, self.sim_time)
            row[f"kappa_{n}"] = values[f"segment{n}.kappa"]
            row[f"theta_{n}"] = values[f"segment{n}.theta"]
            row[f"p_a_{n}"] = values[f"segment{n}.p_a"]
            row[f"p_b_{n}"] = values[f"segment{n}.p_b"]
            row[f"x_{n}"] = values[f"cylinder{n}.x"]
            row[f"x_ref_{n}"] = values[f"drive{n}.x_ref"]
            row[f"v_{n}"] = values[f"cylinder{n}.v"]
            row[f"i_motor_{n}"] = values[f"cylinder{n}.i_motor"]
            row[f"fault_{n}"] = values[f"drive{n}.fault"]
        self.signals.begin_row(self.sim_time, row)


def _clamp(value: float, lo: float, hi: float) -> float:
    return lo if value < lo else hi if value > hi else (value if math.isfinite(value) else 0.0)
