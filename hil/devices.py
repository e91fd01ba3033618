"""Device nodes: everything on the bus that is not the controller (README, "Robots, devices,
protocol").

A device node is a master participant (its outputs drive FMU inputs through connections, its
inputs are FMU outputs) and a bus node. Between SYNCs it only holds its outputs (or, like the
camera, steps at its own rate); its bus life is one small contract:
  - `accepts(frame)` / `receive(frame)`: frames addressed to it, buffered until the next SYNC;
  - `act(sync, inputs)`: at SYNC, from its inputs at that instant, latch what it received, guard
    its own safety, and return the frames it sends, each with its send phase.
The plant sends every node's frames in phase order (emergencies, heartbeats, measurements,
status), nodes in their rig order within a phase. Invariant: a node's outputs change only in
`act` (the plant then publishes them to the master), so the physics between two SYNCs sees
constant commands, as synchronous RPDOs on a CANopen rig.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Protocol

import numpy as np

from hil.cosim import Participant
from hil.vision import Camera, Picture
from rigbus.protocol import (
    COUNTER_MODULO,
    EMCY_COMMAND_TIMEOUT,
    EMCY_OVER_PRESSURE,
    NMT_OPERATIONAL,
    CameraFrame,
    CameraMarker,
    CameraMarker3D,
    DriveCommand,
    DriveStatus,
    Emcy,
    Frame,
    Heartbeat,
)
from rigbus.protocol import Protocol as CanProtocol

# send phases: the documented order of a SYNC's answer
EMERGENCY, HEARTBEAT, MEASUREMENT, STATUS = 0, 1, 2, 3

HEARTBEAT_PERIOD = 1.0  # [s] between heartbeats of every node

FAULT_REF_CLAMPED = 2  # the DriveCylinder's own bits: 1 end stop, 2 setpoint clamped, 4 stall
FAULT_OVER_PRESSURE = 16  # plant-side fault bits, above the DriveCylinder's own 1, 2, 4
FAULT_COMMAND_TIMEOUT = 32


@dataclass(frozen=True, slots=True)
class SyncContext:
    """One SYNC as the devices see it: cycle c, its wire counter, its tick and time."""

    cycle: int
    tick: int
    time: float
    heartbeat: bool = False  # this SYNC is one at which nodes send their heartbeat

    @property
    def counter(self) -> int:
        return self.cycle % COUNTER_MODULO


class DeviceNode(Participant, Protocol):
    """A bus node of the rig that is also a master participant."""

    def accepts(self, frame: Frame) -> bool:
        """Whether this node takes `frame`: by its kind and index alone (its CAN id), as a CAN
        controller's acceptance filter does; the plant asks once per CAN id."""
        ...

    def receive(self, frame: Frame) -> None: ...
    def act(self, sync: SyncContext, inputs: Mapping[str, float]) -> list[tuple[int, Frame]]: ...


def clamp(value: float, lo: float, hi: float) -> float:
    """Saturate as a sensor's ADC would; a non-finite value reads as 0."""
    return lo if value < lo else hi if value > hi else (value if math.isfinite(value) else 0.0)


@dataclass
class DriveNode:
    """Drive n's firmware: at SYNC it latches the last period's command (synchronous RPDO),
    guards its own safety from its inputs (piston position, chamber pressures, the servo's fault
    bits) and answers with its status (and EMCY, heartbeat). Between SYNCs it holds its outputs,
    the servo's setpoint and enable.

    Safety: a command missing for more than `timeout_ticks` holds the piston where it is (EMCY
    0xFF02); a gauge pressure beyond `max_pressure` on either side holds it too (EMCY 0xFF01),
    allowing only moves back towards the sealing position `x_seal`, until both sides fall below
    90 % of the limit. A setpoint outside the stroke is the servo's to clamp (its fault bit 2);
    the drive counts the SYNCs after such a period (`clamped`, the first in `first_clamped`)."""

    node: int
    x_start: float
    x_seal: float
    max_pressure: float
    timeout_ticks: int
    position_range: tuple[float, float] = (-math.inf, math.inf)  # DriveStatus, from the DBC
    pressure_range: tuple[float, float] = (-math.inf, math.inf)
    active_setpoint: float = 0.0
    active_enable: bool = True
    pending: DriveCommand | None = None
    last_command_tick: int = 0
    timed_out: bool = False
    over_pressure: bool = False
    hold_position: float = 0.0
    missed: int = 0
    stale: int = 0
    emcy_sent: int = 0
    clamped: int = 0  # SYNCs after a period whose setpoint the servo clamped to the stroke
    first_clamped: tuple[float, float] | None = None  # (SYNC time [s], setpoint [m])
    servo_fault: int = 0
    decimation: int = 1  # ticks between master steps: its outputs change only at SYNC
    setpoint: float = field(init=False)
    # its step never changes its outputs (they change in `act`, which the plant publishes): the
    # master may step it after the FMUs' tick (hil.cosim.algorithm.Algorithm.start_advance)
    outputs_hold: ClassVar[bool] = True

    def __post_init__(self) -> None:
        self.active_setpoint = self.x_start
        self.setpoint = self.x_start
        self.name = f"drive{self.node}"

    # participant: outputs held between SYNCs, inputs read at SYNC only
    def input_names(self) -> list[str]:
        return ["x", "p_a", "p_b", "servo_fault"]

    def output_names(self) -> list[str]:
        return ["x_ref", "enable", "fault"]

    def set_inputs(self, values: Mapping[str, float]) -> None:
        """Inputs are read at SYNC through `act`; between SYNCs the firmware only holds."""

    def step(self, time: float, step: float) -> None:
        """Nothing happens between SYNCs: the outputs hold."""

    def get_outputs(self) -> dict[str, float]:
        return {
            "x_ref": self.setpoint,
            "enable": 1.0 if self.active_enable else 0.0,
            "fault": float(self.fault),
        }

    @property
    def fault(self) -> int:
        return (self.servo_fault | self.fault_bits) & 0xFF

    @property
    def fault_bits(self) -> int:
        return (FAULT_OVER_PRESSURE if self.over_pressure else 0) | (
            FAULT_COMMAND_TIMEOUT if self.timed_out else 0
        )

    # bus node
    def accepts(self, frame: Frame) -> bool:
        return isinstance(frame, DriveCommand) and frame.node == self.node

    def receive(self, frame: Frame) -> None:
        self.pending = frame

    def act(self, sync: SyncContext, inputs: Mapping[str, float]) -> list[tuple[int, Frame]]:
        """Apply the commands of the last period at this SYNC, from the inputs at this SYNC."""
        x, p_a, p_b = inputs["x"], inputs["p_a"], inputs["p_b"]
        self.servo_fault = int(inputs["servo_fault"])
        if self.servo_fault & FAULT_REF_CLAMPED:  # the setpoint of the period now ending
            self.clamped += 1
            if self.first_clamped is None:
                self.first_clamped = (sync.time, self.setpoint)
        sent: list[tuple[int, Frame]] = []
        expected = (sync.cycle - 1) % COUNTER_MODULO
        if self.pending is not None and self.pending.counter == expected:
            self.active_setpoint = self.pending.piston_setpoint
            self.active_enable = self.pending.enable
            self.last_command_tick = sync.tick
            self.timed_out = False
        elif self.pending is not None:
            self.stale += 1
        elif sync.tick > 0:
            self.missed += 1
        self.pending = None
        if not self.timed_out and sync.tick - self.last_command_tick > self.timeout_ticks:
            self.timed_out = True
            self.hold_position = x
            sent.append(
                (
                    EMERGENCY,
                    Emcy(self.node, EMCY_COMMAND_TIMEOUT, 1, self._pressure(p_a, p_b), sync.cycle),
                )
            )
        pressure = max(abs(p_a), abs(p_b))
        if not self.over_pressure and pressure > self.max_pressure:
            self.over_pressure = True
            sent.append(
                (
                    EMERGENCY,
                    Emcy(self.node, EMCY_OVER_PRESSURE, 1, self._pressure(p_a, p_b), sync.cycle),
                )
            )
        elif self.over_pressure and pressure < 0.9 * self.max_pressure:
            self.over_pressure = False
        setpoint = self.hold_position if self.timed_out else self.active_setpoint
        if self.over_pressure and (setpoint - x) * (self.x_seal - x) <= 0.0:
            setpoint = x  # hold: only moves back towards the sealing position relieve pressure
        self.setpoint = setpoint
        self.emcy_sent += len(sent)
        if sync.heartbeat:
            sent.append((HEARTBEAT, Heartbeat(self.node, NMT_OPERATIONAL)))
        sent.append(
            (
                STATUS,
                DriveStatus(
                    self.node,
                    clamp(x, *self.position_range),
                    clamp(p_a, *self.pressure_range),
                    clamp(p_b, *self.pressure_range),
                    self.fault,
                    sync.cycle,
                ),
            )
        )
        return sent

    def _pressure(self, p_a: float, p_b: float) -> float:
        """The larger gauge pressure, for an EMCY (sent saturated to the DBC's range)."""
        return clamp(max(p_a, p_b), *self.pressure_range)


MarkerModel = Callable[[Sequence[float]], np.ndarray]


class CameraNode:
    """The camera: it takes a picture at each exposure tick (its rate, plus the camera model's
    jitter) of the true shape (the robot's marker model applied to its inputs at that tick),
    through the camera model's imperfections (noise, dropouts, occlusions, outliers), and
    delivers it `latency_ticks` later: a CameraFrame header naming the markers seen, then one
    marker frame per marker seen. Without jitter it steps at its rate only (its decimation)."""

    name = "camera"

    def __init__(
        self,
        inputs: Sequence[str],
        marker_model: MarkerModel,
        latency_ticks: int,
        camera: Camera,
        field: Sequence[tuple[float, float]] | None = None,
        dims: int = 2,
    ) -> None:
        self._inputs = list(inputs)
        # the field of view ((x min, x max), (y min, y max)[, (z min, z max)]) [m], by default
        # what the DBC's marker frames carry: a marker outside it is not seen, as a real camera
        # loses what leaves its image
        if field is None:
            range_of = CanProtocol().signal_range
            message = "CameraMarker0" if dims == 2 else "CameraMarker3D0"
            field = tuple(range_of(message, axis) for axis in "xyz"[:dims])
        if len(field) != dims:
            raise ValueError(f"camera field of view: {len(field)} ranges for {dims} dimensions")
        self.field = tuple(field)
        self.dims = dims  # 2: CameraMarker frames, 3: CameraMarker3D frames
        self.marker_model = marker_model
        self.camera = camera
        self.period_ticks = camera.period_ticks
        self.latency_ticks = latency_ticks
        self.macro_step = camera.macro_step
        self.decimation = 1 if camera.effects.jitter > 0.0 else self.period_ticks
        self.frame_index = 0
        self.next_exposure = camera.exposure_tick(0, 0)
        self.queue: deque[tuple[int, Picture]] = deque()
        self.values = [0.0] * len(self._inputs)
        self._position = {name: i for i, name in enumerate(self._inputs)}

    def input_names(self) -> list[str]:
        return list(self._inputs)

    def output_names(self) -> list[str]:
        return []

    def set_inputs(self, values: Mapping[str, float]) -> None:
        for name, value in values.items():
            self.values[self._position[name]] = value

    def get_outputs(self) -> dict[str, float]:
        return {}

    def step(self, time: float, step: float) -> None:
        """At an exposure tick: a picture of the shape on the inputs (set from the state at
        `time`)."""
        tick = round(time / self.macro_step)
        if tick != self.next_exposure:
            return
        index = self.frame_index
        picture = self.camera.picture(
            index, index * self.period_ticks * self.macro_step, self.marker_model(self.values)
        )
        self.queue.append((picture.exposure_tick + self.latency_ticks, picture))
        self.frame_index += 1
        self.next_exposure = self.camera.exposure_tick(
            self.frame_index, self.frame_index * self.period_ticks
        )

    def _in_view(self, points: list[list[float]]) -> list[int]:
        """The markers seen: inside the field of view and present (no NaN coordinate); on the
        picture's points as floats (a handful of markers: cheaper than array operations). A NaN
        coordinate compares false: not seen."""
        if self.dims == 2:
            (x0, x1), (y0, y1) = self.field
            return [m for m, (x, y) in enumerate(points) if x0 <= x <= x1 and y0 <= y <= y1]
        (x0, x1), (y0, y1), (z0, z1) = self.field
        return [
            m
            for m, (x, y, z) in enumerate(points)
            if x0 <= x <= x1 and y0 <= y <= y1 and z0 <= z <= z1
        ]

    def accepts(self, frame: Frame) -> bool:
        return False

    def receive(self, frame: Frame) -> None:  # pragma: no cover - accepts nothing
        raise AssertionError("the camera receives no frames")

    def act(self, sync: SyncContext, inputs: Mapping[str, float]) -> list[tuple[int, Frame]]:
        """Every picture available by this SYNC, oldest first: its CameraFrame header (which
        markers it holds) and a marker frame for each marker seen."""
        frames: list[tuple[int, Frame]] = []
        while self.queue and self.queue[0][0] <= sync.tick:
            _, picture = self.queue.popleft()
            index, points = picture.frame_index, picture.points
            offset = (sync.tick - picture.exposure_tick) * self.macro_step
            rows = points.tolist()
            seen = self._in_view(rows)
            mask = sum(1 << m for m in seen)
            frames.append((MEASUREMENT, CameraFrame(index, offset, mask, len(seen))))
            if self.dims == 2:
                for m in seen:
                    marker = CameraMarker(m, rows[m][0], rows[m][1], index, offset)
                    frames.append((MEASUREMENT, marker))
            else:
                for m in seen:
                    x, y, z = rows[m]
                    frames.append((MEASUREMENT, CameraMarker3D(m, index, x, y, z)))
        return frames
