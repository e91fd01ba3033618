"""The controller node: a separate program that sees the rig only through the CAN bus.

It is the SYNC producer (as a CANopen master on a rig). Cycle c:
  1. wait for the period (real-time clock) or not at all (lockstep), send SYNC(c);
  2. collect what cycle c must bring, known from the frames themselves and the devices'
     announced rates, never from the order in which they arrive (on a real bus the lower ids win
     arbitration): every drive's status frame echoing c, and every camera frame whose exposure
     plus latency falls at or before this SYNC (partial camera frames are kept until complete);
  3. hand the cycle's drive readings and completed camera frames to the robot's `Estimator`,
     the estimate to the robot's `Controller`, and send the frames it returns;
then SYNC(c+1). Commands computed from the status of c act from SYNC(c+1): one control period of
computation delay, as on a rig. Missing or stale frames follow the policy: `strict` stops with an
error naming the frame, `hold` keeps the last value and counts the miss.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import typing
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from controllers.curvature import PiGains
from controllers.estimation import (
    BendModel,
    CameraNoise,
    Controller,
    Estimator,
    MarkerFrame,
)
from controllers.gripper import GripperGeometry
from controllers.tasks import TaskPlan
from controllers.trajectories import CurvatureProfile, Sine
from rigbus.canbus import connection_closed, failure_text, send_all
from rigbus.protocol import (
    COUNTER_MODULO,
    CameraFrame,
    CameraMarker,
    ControllerState,
    DriveCommand,
    Emcy,
    FrameError,
    GenericFrame,
    Heartbeat,
    Protocol,
    Sync,
    TaskState,
    frame_key,
)

POLICIES = ("strict", "hold")
OWN_FRAMES = (
    Sync,
    DriveCommand,
    ControllerState,
    TaskState,
)  # the frames only the controller sends
OWN_KINDS = ("ValveCommand", "FishState")  # and those of kinds with no registered type
ESTIMATORS = ("raw", "kf", "ukf")


class ControllerError(RuntimeError):
    """The controller cannot go on; the message names the frame, cycle or peer."""


@dataclass(frozen=True)
class CameraTiming:
    """When camera frames become available, in macro-step ticks: frame j is exposed at tick
    j * period_ticks, up to delay_ticks later (exposure jitter), and available latency_ticks
    after its exposure; SYNC c is at tick c * control_ticks. A frame is due at the first SYNC by
    which it is available however late its exposure: waiting for it earlier would wait on a
    frame the camera has not taken yet (the count, not the order of arrival, decides)."""

    period_ticks: int
    latency_ticks: int
    control_ticks: int
    markers: int
    delay_ticks: int = 0  # the latest an exposure falls after its nominal tick (jitter)

    def __post_init__(self) -> None:
        """ValueError naming the key for timing no camera has (every robot's config)."""
        if min(self.period_ticks, self.control_ticks) < 1 or self.latency_ticks < 0:
            raise ValueError("camera_timing: period_ticks and control_ticks must be at least 1")
        if not 0 <= self.delay_ticks < self.period_ticks:
            raise ValueError(
                f"camera_timing.delay_ticks: {self.delay_ticks} is outside 0..period_ticks - 1"
            )

    def frames_due(self, cycle: int) -> int:
        """How many frames (0, 1, ... j) are available by SYNC `cycle`, however late their
        exposure."""
        tick = cycle * self.control_ticks - self.latency_ticks - self.delay_ticks
        return 0 if tick < 0 else tick // self.period_ticks + 1


@dataclass(frozen=True)
class GripperConfig:
    """The gripper's drive (node) and the piston positions [m] that start, open and close it."""

    node: int
    x_start: float
    x_open: float
    x_closed: float
    geometry: GripperGeometry = GripperGeometry()


@dataclass(frozen=True)
class ControllerConfig:
    """Everything the planar arm's controller knows about the rig and its task (written by
    `hil run` as controller.json); per-segment values are tuples, segment 1 first."""

    robot: str
    lengths: tuple[float, ...]
    base: tuple[float, float, float]
    control_period: float
    cycles: int
    x_mid: tuple[float, ...]
    x_min: tuple[float, ...]
    x_max: tuple[float, ...]
    gains: tuple[PiGains, ...]
    profile: CurvatureProfile
    bends: tuple[BendModel, ...]
    camera: CameraNoise
    camera_timing: CameraTiming
    feedforward: tuple[float, ...] = ()  # piston offset per unit curvature reference [m per 1/m]
    policy: str = "strict"
    timeout: float = 10.0  # wall-clock wait for a cycle's frames [s]
    estimator: str = "raw"
    latency_compensation: bool = True
    torque_std: float | None = None  # the estimator's unmodelled torque std [N m]; None: derived
    plan: TaskPlan | None = None  # task-space task (point-to-point, path); None: the profile
    objects: int = 0  # object markers the camera reports after the arm's (ids segments + 1 ...)
    gripper: GripperConfig | None = None  # the finger pair at the tip and its drive

    @property
    def segments(self) -> int:
        return len(self.lengths)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ControllerConfig:
        """Read a config; wrong or missing keys raise ValueError naming the key."""
        config: ControllerConfig = config_from_json(cls, text)
        if config.estimator not in ESTIMATORS:
            raise ValueError(
                f"estimator: {config.estimator!r} is not one of {', '.join(ESTIMATORS)}"
            )
        n = config.segments
        for name in ("x_mid", "x_min", "x_max", "gains", "bends", "feedforward"):
            if len(getattr(config, name)) != n:
                raise ValueError(f"{name}: {len(getattr(config, name))} values for {n} segments")
        if config.control_period <= 0 or config.cycles < 0 or config.timeout <= 0:
            raise ValueError("control_period and timeout must be positive, cycles not negative")
        _check_ranges(config)
        if config.plan is not None:
            _check_plan(config.plan, n)
        return config


# The robot kinds' controller sides: each module provides its config class (`config_class`,
# with `from_json` and `to_json`), `make_estimator(config)`, `make_controller(config, protocol)`,
# `expected(config)` (the (DBC kind, index) of the status frames every cycle must bring) and
# `readings(status)` (what the estimator and controller see of those frames).
ROBOT_MODULES = {"planar_arm": "controllers.planar_arm", "fish": "controllers.fish"}


def robot_module(robot: str) -> Any:
    """The controller-side module of robot kind `robot`; ValueError naming the known kinds."""
    import importlib

    if robot not in ROBOT_MODULES:
        raise ValueError(f"robot: {robot!r} is not one of {', '.join(ROBOT_MODULES)}")
    return importlib.import_module(ROBOT_MODULES[robot])


def read_config(text: str) -> Any:
    """A controller configuration of any robot kind, by its `robot` key (default planar_arm);
    ValueError naming the key otherwise."""
    data = json.loads(text)
    if not isinstance(data, dict):
        raise ValueError("must be a JSON object")
    robot = data.get("robot", "planar_arm")
    if not isinstance(robot, str):
        raise ValueError(f"robot: must be a string, got {robot!r}")
    return robot_module(robot).config_class.from_json(text)


# The ranges `hil run` validates a scenario against (hil/scenario.py), for a config written by
# hand: control period 1 us .. 1 s, at most 10 million cycles, a wait of at most an hour, and
# gains within the DBC's piston range (0.1 m) per 0.01 1/m of curvature error.
CONTROL_PERIOD_RANGE = (1e-6, 1.0)
MAX_CYCLES = 10_000_000
MAX_TIMEOUT = 3_600.0
KP_MAX = 0.1 / 0.01


def _check_ranges(config: ControllerConfig) -> None:
    lo, hi = CONTROL_PERIOD_RANGE
    if not lo <= config.control_period <= hi:
        raise ValueError(f"control_period: {config.control_period:g} s is outside {lo:g}..{hi:g}")
    if config.cycles > MAX_CYCLES:
        raise ValueError(f"cycles: {config.cycles} is beyond {MAX_CYCLES}")
    if config.timeout > MAX_TIMEOUT:
        raise ValueError(f"timeout: {config.timeout:g} s is beyond {MAX_TIMEOUT:g} s")
    if any(length <= 0 for length in config.lengths):
        raise ValueError("lengths: must be positive")
    for i, gains in enumerate(config.gains):
        if not 0 <= gains.Kp <= KP_MAX:
            raise ValueError(f"gains[{i}].Kp: {gains.Kp:g} is outside 0..{KP_MAX:g}")
        if not 0 <= gains.Ki <= KP_MAX / config.control_period:
            raise ValueError(
                f"gains[{i}].Ki: {gains.Ki:g} is outside 0..{KP_MAX / config.control_period:g}"
            )
    timing = config.camera_timing  # its own ranges: CameraTiming.__post_init__
    if config.torque_std is not None and not config.torque_std > 0:
        raise ValueError(f"torque_std: must be positive, got {config.torque_std}")
    if config.objects < 0:
        raise ValueError("objects: must not be negative")
    if timing.markers != config.segments + 1 + config.objects:
        raise ValueError(
            f"camera_timing.markers: must be {config.segments + 1 + config.objects} "
            "(segments + 1 + objects)"
        )
    if config.gripper is not None and config.gripper.node <= config.segments:
        raise ValueError("gripper.node: must follow the segments' drives")


def _check_plan(plan: TaskPlan, segments: int) -> None:
    from controllers.tasks import TASK_KINDS

    if plan.kind not in TASK_KINDS:
        raise ValueError(f"plan.kind: {plan.kind!r} is not one of {', '.join(TASK_KINDS)}")
    if not plan.targets:
        raise ValueError("plan.targets: no target")
    if plan.kind == "path" and len(plan.ends) != len(plan.targets):
        raise ValueError(f"plan.ends: {len(plan.ends)} ends for {len(plan.targets)} paths")
    for name in ("kappa_min", "kappa_max", "kappa_rate"):
        if len(getattr(plan, name)) != segments:
            raise ValueError(
                f"plan.{name}: {len(getattr(plan, name))} values for {segments} segments"
            )
    if any(lo >= hi for lo, hi in zip(plan.kappa_min, plan.kappa_max, strict=True)):
        raise ValueError("plan.kappa_min: must be below plan.kappa_max")
    for name in ("kappa_rate",):
        if any(v <= 0 for v in getattr(plan, name)):
            raise ValueError(f"plan.{name}: must be positive")
    for name in ("tolerance", "settle_time", "max_time", "speed", "acceleration", "accel_time"):
        if getattr(plan, name) <= 0:
            raise ValueError(f"plan.{name}: must be positive")


def config_from_json(cls: Any, text: str) -> Any:
    """A robot's controller configuration (a dataclass with a `policy`) from its JSON text:
    every key and type checked, ValueError naming the key; the robot checks the rest."""
    data = json.loads(text)
    if not isinstance(data, dict):
        raise ValueError("must be a JSON object")
    config = _from_data(cls, data, "")
    if config.policy not in POLICIES:
        raise ValueError(f"policy: {config.policy!r} is not one of {', '.join(POLICIES)}")
    return config


def _from_data(cls: Any, data: Any, key: str) -> Any:
    """A dataclass from JSON data, checking every key and type (ValueError naming the key)."""
    hints = typing.get_type_hints(cls)
    if not isinstance(data, dict):
        raise ValueError(f"{key or 'config'}: must be an object")
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(known)
    if unknown:
        raise ValueError(f"{key + '.' if key else ''}{sorted(unknown)[0]}: unknown key")
    values = {}
    for name, f in known.items():
        sub = f"{key}.{name}" if key else name
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ValueError(f"{sub}: missing key")
            continue
        values[name] = _value(hints[name], data[name], sub)
    return cls(**values)


def _value(hint: Any, raw: Any, key: str) -> Any:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, __import__("types").UnionType):
        if raw is None and type(None) in args:
            return None
        return _value(next(a for a in args if a is not type(None)), raw, key)
    if hint is bool:
        if not isinstance(raw, bool):
            raise ValueError(f"{key}: must be true or false, got {raw!r}")
        return raw
    if hint is int:
        if isinstance(raw, bool) or not isinstance(raw, int):
            raise ValueError(f"{key}: must be an integer, got {raw!r}")
        return raw
    if hint is float:
        if isinstance(raw, bool) or not isinstance(raw, int | float):
            raise ValueError(f"{key}: must be a number, got {raw!r}")
        try:
            value = float(raw)
        except OverflowError:
            raise ValueError(f"{key}: must be finite, got {raw!r}") from None
        if not math.isfinite(value):
            raise ValueError(f"{key}: must be finite, got {raw!r}")
        return value
    if hint is str:
        if not isinstance(raw, str):
            raise ValueError(f"{key}: must be a string, got {raw!r}")
        return raw
    if origin is tuple:
        if not isinstance(raw, list):
            raise ValueError(f"{key}: must be a list, got {raw!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_value(args[0], v, f"{key}[{i}]") for i, v in enumerate(raw))
        if len(raw) != len(args):
            raise ValueError(f"{key}: must have {len(args)} elements")
        return tuple(
            _value(a, v, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, raw, strict=True))
        )
    if dataclasses.is_dataclass(hint):
        return _from_data(hint, raw, key)
    raise ValueError(f"{key}: unsupported type {hint}")  # pragma: no cover - schema bug


_ = Sine  # the profile's sine is read through _from_data


@dataclass
class ControllerReport:
    """What the controller counted; written as JSON at the end of a run."""

    cycles: int = 0
    status_missed: int = 0
    stale_frames: int = 0
    unknown_frames: int = 0
    camera_frames: int = 0
    camera_frames_incomplete: int = 0
    emcy: list[dict[str, Any]] = field(default_factory=list)
    realtime: bool = False
    max_lateness: float = 0.0
    mean_lateness: float = 0.0
    overruns: int = 0
    frames_sent: int = 0
    frames_received: int = 0
    intrusions: int = 0  # frames in the controller's (or a drive's) name that it did not send
    first_intrusion: str = ""
    notes: list[str] = field(default_factory=list)  # what the task wants told (summary warnings)


class LockstepClock:
    """As fast as possible: the next SYNC goes out as soon as the cycle's work is done."""

    realtime = False

    def wait_for(self, cycle: int) -> float:
        return 0.0


class RealtimeClock:
    """SYNC(c) at wall-clock t0 + c T; returns the lateness of each SYNC [s]. `sleep` and
    `monotonic` are injectable so the pacing can be tested without waiting."""

    realtime = True

    def __init__(
        self,
        period: float,
        sleep: Callable[[float], None] = time.sleep,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.period = period
        self.start: float | None = None
        self._sleep = sleep
        self._monotonic = monotonic

    def wait_for(self, cycle: int) -> float:
        now = self._monotonic()
        if self.start is None:
            self.start = now
        deadline = self.start + cycle * self.period
        if deadline > now:
            self._sleep(deadline - now)
            now = self._monotonic()
        return max(0.0, now - deadline)


_UNSEEN_MARKER = (math.nan, math.nan)  # a marker a picture does not hold


class CameraAssembler:
    """Collects each camera picture: its CameraFrame header says which markers it holds; the
    picture is complete when all of them have arrived, in whatever order."""

    def __init__(self, markers: int) -> None:
        self.markers = markers
        self._all_markers = (1 << markers) - 1  # the mask bits of markers 0 .. markers - 1
        self._headers: dict[int, CameraFrame] = {}
        self._pending: dict[int, dict[int, CameraMarker]] = {}

    def add(self, frame: CameraFrame | CameraMarker) -> None:
        if isinstance(frame, CameraFrame):
            self._headers[frame.frame_index] = frame
        elif 0 <= frame.marker_id < self.markers:
            self._pending.setdefault(frame.frame_index, {})[frame.marker_id] = frame

    def complete(self, index: int) -> bool:
        header = self._headers.get(index % COUNTER_MODULO)
        if header is None:
            return False
        have = self._pending.get(index % COUNTER_MODULO, {})
        mask = header.marker_mask & self._all_markers
        # asked after every frame of a picture: fewer markers in than it holds is the usual
        # answer, found without the look-ups
        if len(have) < mask.bit_count():
            return False
        return all(m in have for m in range(self.markers) if mask >> m & 1)

    def take(self, index: int, sync_time: float) -> MarkerFrame:
        """The picture `index` (complete) stamped with its exposure time; markers it does not
        hold are NaN."""
        key = index % COUNTER_MODULO
        header = self._headers.pop(key)
        frame = self._pending.pop(key, {})
        # the rows as floats, one array made of them (not a row assignment per marker)
        rows = [_UNSEEN_MARKER] * self.markers
        for m, marker in frame.items():
            if header.marker_mask >> m & 1:
                rows[m] = (marker.x, marker.y)
        points = np.array(rows, dtype=float)
        return MarkerFrame(exposure_time=sync_time - header.exposure_offset, points=points)

    def drop(self, index: int) -> bool:
        """Forget a picture that will not complete; True if part of it had arrived."""
        key = index % COUNTER_MODULO
        had = key in self._headers or key in self._pending
        self._headers.pop(key, None)
        self._pending.pop(key, None)
        return had


class ControllerNode:
    """The controller bound to a bus; `run()` drives the whole experiment."""

    def __init__(
        self,
        config: ControllerConfig,
        bus: can.BusABC,
        clock: LockstepClock | RealtimeClock | None = None,
        protocol: Protocol | None = None,
        estimator: Estimator | None = None,
        controller: Controller | None = None,
    ) -> None:
        if config.policy not in POLICIES:
            raise ControllerError(f"policy {config.policy!r}: must be one of {POLICIES}")
        module = robot_module(config.robot)

        self.config = config
        self.module = module
        self.bus = bus
        self.clock = clock or LockstepClock()
        self.protocol = protocol or Protocol()
        self.report = ControllerReport(realtime=self.clock.realtime)
        self.camera = CameraAssembler(config.camera_timing.markers)
        self.estimator = estimator or module.make_estimator(config)
        self.controller = controller or module.make_controller(config, self.protocol)
        self.expected: set[tuple[str, int | None]] = module.expected(config)
        self.status: dict[tuple[str, int | None], Any] = {}
        self._status_kinds = {kind for kind, _ in self.expected}
        self._frames_taken = 0  # camera frames 0 .. _frames_taken - 1 are done with
        self._outbox: list[can.Message] = []  # encoded, not yet sent (`_flush`)
        self._outbox_time = 0.0
        self._routes: dict[int, tuple[str, tuple[str, int | None]]] = {}  # by CAN id (`_route`)

    def _send(self, frame: Any, sim_time: float) -> None:
        """Queue one frame; `_flush` sends the queue in order."""
        self._outbox.append(self.protocol.encode(frame, timestamp=sim_time))
        self._outbox_time = sim_time

    def _flush(self) -> None:
        """Send the queued frames in order, in one write where the bus can (`send_all`)."""
        messages, self._outbox = self._outbox, []
        if not messages:
            return
        try:
            send_all(self.bus, messages)
        except (OSError, can.CanError) as exc:
            ids = ", ".join(f"0x{m.arbitration_id:03X}" for m in messages)
            raise ControllerError(
                f"sending {ids} at t = {self._outbox_time:.3f} s: the bus is gone ({exc})"
            ) from exc
        self.report.frames_sent += len(messages)

    def run(self) -> ControllerReport:
        """Run every cycle of the experiment; raises ControllerError under the strict policy.
        In lockstep on a bus that sends batches (softhil's binary records), a cycle's commands
        go out with the next SYNC, in one write: nothing can tell the difference (the plant
        latches commands at SYNC, and the order of frames is the same), and it halves the
        writes and hub wake-ups per cycle. Otherwise (the real-time clock, as on a rig; other
        buses, where it would save nothing) they go out as soon as they are computed."""
        T = self.config.control_period
        lateness = []
        batching = not self.clock.realtime and hasattr(self.bus, "send_batch")
        for cycle in range(self.config.cycles + 1):
            lateness.append(self.clock.wait_for(cycle))
            t = cycle * T
            self._send(Sync(cycle), t)
            self._flush()
            frames = self._collect(cycle, t)
            self.report.cycles = cycle
            if cycle == self.config.cycles:
                break  # the final SYNC lets the plant reach the end time; nothing acts after it
            readings = self.module.readings(self.status)
            estimate = self.estimator.update(t, readings, frames)
            for frame in self.controller.compute(cycle, t, estimate, readings):
                self._send(frame, t)
            if not batching:
                self._flush()
        self.report.notes = [str(n) for n in getattr(self.controller, "notes", ())]
        if lateness:
            self.report.max_lateness = max(lateness)
            self.report.mean_lateness = float(np.mean(lateness))
            self.report.overruns = sum(1 for late in lateness if late > T)
        return self.report

    def _intrusion(self, what: str) -> None:
        """Count a frame that its one legitimate sender did not send; strict stops."""
        if self.config.policy == "strict":
            raise ControllerError(f"intrusion on the bus: {what}")
        self.report.intrusions += 1
        if not self.report.first_intrusion:
            self.report.first_intrusion = what

    def _route(self, frame: Any) -> tuple[str, tuple[str, int | None]]:
        """What `_collect` does with the frames of `frame`'s CAN id (a CAN id always decodes
        to the same kind and index, so this is found once per id), and their (kind, index)."""
        key = frame_key(frame)
        if key[0] in self._status_kinds:
            return _STATUS, key
        if isinstance(frame, CameraMarker | CameraFrame):
            return _CAMERA, key
        if isinstance(frame, Emcy):
            return _EMCY, key
        if isinstance(frame, Heartbeat):
            return _HEARTBEAT, key
        if isinstance(frame, OWN_FRAMES) or (
            isinstance(frame, GenericFrame) and frame.kind in OWN_KINDS
        ):
            return _OWN, key
        return _OTHER, key

    def _collect(self, cycle: int, t: float) -> list[MarkerFrame]:
        """Receive until the cycle holds every status frame echoing it and every camera frame
        due by this SYNC; returns the camera frames completed, oldest first."""
        config = self.config
        needed = set(self.expected)
        due = config.camera_timing.frames_due(cycle)
        deadline = time.monotonic() + config.timeout
        counter = cycle % COUNTER_MODULO

        def camera_complete() -> bool:
            return all(self.camera.complete(j) for j in range(self._frames_taken, due))

        while needed or not camera_complete():
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                missing = [_name(key) for key in sorted(needed, key=_name)]
                missing += [
                    f"camera frame {j}"
                    for j in range(self._frames_taken, due)
                    if not self.camera.complete(j)
                ]
                if config.policy == "strict":
                    raise ControllerError(
                        f"no {', '.join(missing)} for SYNC {cycle} (t = {t:.3f} s) within "
                        f"{config.timeout:g} s: is the plant running?"
                    )
                self.report.status_missed += len(needed)
                break
            try:
                message = self.bus.recv(timeout=min(remaining, 0.5))
            except (can.CanError, OSError) as exc:
                raise ControllerError(
                    f"the bus failed while waiting for SYNC {cycle}'s status "
                    f"({failure_text(exc)}): the plant and its hub are gone?"
                ) from None
            if message is None:
                if connection_closed(self.bus):
                    raise ControllerError(
                        f"the bus closed while waiting for SYNC {cycle}'s status: the plant "
                        "and its loopback hub are gone"
                    )
                continue
            self.report.frames_received += 1
            try:
                frame = self.protocol.decode(message)
            except FrameError as exc:
                if config.policy == "strict":
                    raise ControllerError(f"at SYNC {cycle}: {exc}") from exc
                self.report.unknown_frames += 1
                continue
            route = self._routes.get(message.arbitration_id)
            if route is None:
                route = self._routes[message.arbitration_id] = self._route(frame)
            what, key = route
            if what is _STATUS:
                # the echoed counter, without building every signal's value (frame_signals)
                echo = int(
                    frame.signals["counter"] if isinstance(frame, GenericFrame) else frame.counter
                )
                if echo == counter and key not in needed:
                    self._intrusion(
                        f"a second {_name(key)} for SYNC {cycle}: another node "
                        f"sends in the {_SENDER.get(key[0], 'device')}'s name"
                    )
                    continue
                if echo != counter or key not in needed:
                    if config.policy == "strict":
                        raise ControllerError(
                            f"stale {_name(key)} (counter {echo}) while "
                            f"waiting for SYNC {cycle} (counter {counter})"
                        )
                    self.report.stale_frames += 1
                    continue
                self.status[key] = frame
                needed.discard(key)
            elif what is _CAMERA:
                self.camera.add(frame)
            elif what is _EMCY:
                self.report.emcy.append({"cycle": cycle, **asdict(frame)})
            elif what is _HEARTBEAT:
                continue
            elif what is _OWN:
                # no bus echoes a sender's own frames: these come from another node
                self._intrusion(
                    f"{type(frame).__name__} 0x{message.arbitration_id:03X} at SYNC {cycle} from "
                    "another node: only this controller sends it"
                )
            elif config.policy == "strict":
                raise ControllerError(
                    f"unexpected {type(frame).__name__} at SYNC {cycle}: is another controller "
                    "on the bus?"
                )
            else:
                self.report.unknown_frames += 1
        frames = []
        for j in range(self._frames_taken, due):
            if self.camera.complete(j):
                frames.append(self.camera.take(j, t))
                self.report.camera_frames += 1
            elif self.camera.drop(j):
                self.report.camera_frames_incomplete += 1
        self._frames_taken = max(self._frames_taken, due)
        return frames


# what `_collect` does with a received frame (`ControllerNode._route`)
_STATUS, _CAMERA, _EMCY, _HEARTBEAT, _OWN, _OTHER = (
    "status",
    "camera",
    "emcy",
    "heartbeat",
    "own",
    "other",
)
_SENDER = {"DriveStatus": "drive", "ValveStatus": "valve", "CanisterStatus": "canister"}


def _name(key: tuple[str, int | None]) -> str:
    """The DBC message name of (kind, index): DriveStatus3, CanisterStatus."""
    return f"{key[0]}{'' if key[1] is None else key[1]}"


def write_report(report: ControllerReport, path: Path) -> None:
    path.write_text(json.dumps(asdict(report), indent=2, sort_keys=True) + "\n")
