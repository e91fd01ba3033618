"""Scenarios: TOML files that say what to run, validated completely before anything runs.

A scenario names the robot (its FMUs and parameters), extra connections, rates, bus, camera,
safety limits, controller and task, seed and duration. `load_scenario` returns a frozen
`Scenario` or raises `ScenarioError` with one line naming the file, the key and the reason
(unknown key, wrong type, missing FMU, impossible rate, value out of range). The built-in
scenarios ship with the robot kinds: every `robots/<kind>/scenarios/*.toml`, named by its file
stem (`builtin_scenarios`, `resolve_scenario`); `default` is the one `hil run` runs.
"""

from __future__ import annotations

import math
import re
import tomllib
import types
import typing
from dataclasses import MISSING, dataclass, fields, replace
from importlib.resources import files
from pathlib import Path
from typing import Any

from hil.errors import HilError, ScenarioError
from hil.results import is_result_file
from hil.seam import ESTIMATORS, POLICIES, CurvatureProfile, Sine
from hil.vision import CameraEffects, check_effects
from rigbus.canbus import KINDS as BUS_KINDS
from rigbus.protocol import Protocol

# the built-in scenarios: each robot kind's folder of them
SCENARIO_FOLDERS = tuple(sorted(Path(str(files("robots"))).glob("*/scenarios")))
DEFAULT_SCENARIO = Path(str(files("robots"))) / "planar_arm" / "scenarios" / "default.toml"
# [bit/s] classical CAN (ISO 11898-1) runs at most 1 Mbit/s; softhil's frames are classical, so
# the bus load and frame times are computed at one bitrate
MAX_BITRATE = 1_000_000
DEFAULT_LOG_START = "2015-06-01T00:00:00Z"  # the thesis's year; see RecordingSpec
_NAME = re.compile(r"[A-Za-z0-9_.-]+")


@dataclass(frozen=True)
class TimingSpec:
    step: float = 1e-3  # plant macro step h [s]
    control_period: float = 1e-2  # SYNC period T [s], an integer multiple of step


class RobotSection:
    """Marker type of the scenario's [robot] section: its schema is the robot kind's
    `spec_class`, chosen by its `kind` key (default planar_arm)."""


@dataclass(frozen=True)
class RecordingSpec:
    """What a run records and how its logs are stamped."""

    # CAN log timestamps are this instant plus simulation time ("now": the wall clock at start);
    # the default is fixed so that reruns give byte-identical logs
    start: str = DEFAULT_LOG_START
    can_log: str = "can.log"  # file name; its suffix picks python-can's writer
    mf4: bool = False  # also write the signals as MF4 (needs asammdf)


@dataclass(frozen=True)
class ConnectionSpec:
    source: str  # "participant.variable"
    target: str
    gain: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True)
class BusConfig:
    kind: str = "loopback"
    channel: str = "softhil"
    host: str = "127.0.0.1"
    port: int = 0  # 0: `hil run` serves its own hub on a free port
    bitrate: int = 1_000_000
    allow_remote: bool = False  # a host beyond 127.0.0.1 (0.0.0.0, another machine) needs it


@dataclass(frozen=True)
class CameraSpec:
    """The camera (PHYSICS.md section 5): SI units, 0 switches an effect off. The defaults are a
    realistic commercial motion-capture system, not an ideal camera."""

    rate: float = 100.0  # [Hz]
    latency: float = 0.006  # exposure to availability [s]
    noise: float = 0.5e-3  # isotropic marker position standard deviation [m]
    dropout: float = 0.01  # per-marker probability of a missing marker
    occlusion_interval: float = 0.0  # mean time between occlusion bursts [s]
    occlusion_duration: float = 0.0  # [s]
    occlusion_scope: str = "frame"  # a burst hides the whole "frame" or one "marker"
    outlier_rate: float = 0.001  # per-marker probability of a displaced marker
    outlier_distance: float = 0.02  # [m]
    jitter: float = 0.0  # exposure-time jitter standard deviation [s]

    def effects(self) -> CameraEffects:
        return CameraEffects(
            noise=self.noise,
            dropout=self.dropout,
            occlusion_interval=self.occlusion_interval,
            occlusion_duration=self.occlusion_duration,
            occlusion_scope=self.occlusion_scope,
            outlier_rate=self.outlier_rate,
            outlier_distance=self.outlier_distance,
            jitter=self.jitter,
        )


@dataclass(frozen=True)
class SafetySpec:
    max_pressure: float = 60e3  # gauge [Pa]: beyond it the drive holds and sends EMCY
    command_timeout: float = 0.1  # [s] without a command: hold and EMCY


@dataclass(frozen=True)
class ControllerSpec:
    kp: float | None = None  # [m per 1/m]; None: designed from the segment physics
    ki: float | None = None  # [m per (1/m) s]
    crossover: float = 1.0  # [Hz] for the designed gains
    feedforward: bool = True  # static inverse of the segment's curvature per piston travel
    policy: str = "strict"
    timeout: float = 10.0  # wall-clock wait for a peer [s]
    estimator: str = "ukf"  # raw, kf or ukf (see README: ukf measures best on the default)
    latency_compensation: bool = True  # fuse camera frames at their exposure time
    # the estimator's unmodelled torque standard deviation [N m]; None: derived per segment from
    # table friction and pressure quantisation (a held object's load needs more)
    torque_std: float | None = None
    # real-time runs fail when a SYNC is later than max_lateness [s] (0: one control period), or
    # when more than the fraction max_overruns of SYNCs is over one control period late
    max_lateness: float = 0.0
    max_overruns: float = 0.01


@dataclass(frozen=True)
class SineSpec:
    start: float
    amplitude: float
    frequency: float
    offset: float = 0.0


@dataclass(frozen=True)
class TaskSpec:
    """The task: a curvature profile per segment (`curvature_profile`), or in task space
    (`point_to_point`, `path`: README, "Task space"). Lengths in m, times in s."""

    kind: str = "curvature_profile"
    steps: tuple[tuple[float, float], ...] = ()
    sine: SineSpec | None = None
    scale: tuple[float, ...] = (1.0,)
    # task space: targets [x, y] or paths [x0, y0, x1, y1]; empty: `count` drawn from the seed
    targets: tuple[tuple[float, float], ...] = ()
    paths: tuple[tuple[float, float, float, float], ...] = ()
    count: int = 8
    margin: float = 0.7  # share of each segment's reachable curvature range drawn targets use
    path_length: float = 0.08  # drawn paths
    tolerance: float = 1e-3  # estimated tip within it: on target
    settle_time: float = 0.5  # on target this long: settled, next target
    max_time: float = 6.0  # per target before the controller gives up on it
    speed: float = 0.01  # path speed [m/s]
    acceleration: float = 0.02  # path acceleration [m/s^2]
    task_gain: float = 1.0  # integral gain on the estimated tip error [1/s]
    band: float = 2e-3  # settling band of the time_to_settle metric
    # confined spaces (kind "pipe"): the goal deep in the channel of [robot.environment] walls,
    # the centreline the tip follows, and the clearance the plan keeps beyond the arm's width
    goal: tuple[float, float] | None = None
    centreline: tuple[tuple[float, float], ...] = ()
    clearance: float = 2e-3
    # grasp-and-place (kind "grasp"): where the object starts (`pick`) and where it goes
    # (`place`), each drawn from the seed unless given; the fingers' closing and opening time
    pick: tuple[float, float] | None = None
    place: tuple[float, float] | None = None
    grasp_time: float = 1.0

    def profile(self) -> CurvatureProfile:
        """The reference profile that the controller tracks and the plant scores against."""
        sine = self.sine
        return CurvatureProfile(
            steps=self.steps,
            sine=None
            if sine is None
            else Sine(sine.start, sine.amplitude, sine.frequency, sine.offset),
            scale=self.scale,
        )


@dataclass(frozen=True)
class Scenario:
    name: str
    seed: int
    duration: float
    description: str = ""
    timing: TimingSpec = TimingSpec()
    robot: Any = None  # the robot kind's spec (RobotSection in the schema)
    connections: tuple[ConnectionSpec, ...] = ()
    bus: BusConfig = BusConfig()
    camera: CameraSpec = CameraSpec()
    safety: SafetySpec = SafetySpec()
    controller: ControllerSpec = ControllerSpec()
    task: TaskSpec = TaskSpec()
    recording: RecordingSpec = RecordingSpec()
    source: str = "<built-in>"

    @property
    def control_ticks(self) -> int:
        return round(self.timing.control_period / self.timing.step)

    @property
    def cycles(self) -> int:
        return round(self.duration / self.timing.control_period)

    @property
    def camera_ticks(self) -> int:
        return round(1.0 / (self.camera.rate * self.timing.step))

    @property
    def latency_ticks(self) -> int:
        return round(self.camera.latency / self.timing.step)


# a table's TOML key -> its field's name, where Python needs another name ("from")
_ALIASES: dict[type, dict[str, str]] = {ConnectionSpec: {"from": "source", "to": "target"}}
# keys whose absence means "draw from the seed": given, they must not be empty
_NOT_EMPTY: dict[type, dict[str, str]] = {
    TaskSpec: {
        "targets": "must not be empty (leave it out to draw task.count targets from the seed)",
        "paths": "must not be empty (leave it out to draw task.count paths from the seed)",
    }
}


def load_scenario(path: Path | None = None, *, seed: int | None = None) -> Scenario:
    """Read and validate a scenario file (the built-in default when `path` is None)."""
    source = path or DEFAULT_SCENARIO
    try:
        data = tomllib.loads(source.read_bytes().decode("utf-8"))
    except FileNotFoundError:
        raise ScenarioError(f"{source}: no such scenario file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{source}: cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: not valid TOML: {exc}") from None
    if "source" in data:
        raise _fail(str(source), "source", "unknown key (the file's own path is implied)")
    scenario = _build(Scenario, {**data, "source": str(source)}, str(source), "")
    if seed is not None:
        if seed < 0:
            raise ScenarioError(f"--seed: must not be negative, got {seed}")
        scenario = replace(scenario, seed=seed)
    _check(scenario)
    return scenario


@dataclass(frozen=True)
class BuiltinScenario:
    """A scenario shipped in `robots/<kind>/scenarios/`: `hil run NAME` runs it."""

    name: str  # the file stem
    path: Path
    description: str  # its `description` key ("" where it has none or cannot be read)


def builtin_scenarios() -> dict[str, BuiltinScenario]:
    """Every `*.toml` in the robot kinds' scenario folders, by name (the file stem), sorted.

    Only the `description` is read here; a broken file is still listed (with no description)
    so that `hil run NAME` reports its problem with the file, key and reason."""
    found: dict[str, BuiltinScenario] = {}
    paths = [path for folder in SCENARIO_FOLDERS for path in folder.glob("*.toml")]
    for path in sorted(paths, key=lambda p: p.name):
        try:
            description = tomllib.loads(path.read_text(encoding="utf-8")).get("description", "")
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            description = ""
        text = description if isinstance(description, str) else ""
        found[path.stem] = BuiltinScenario(path.stem, path, " ".join(text.split()))
    return found


def resolve_scenario(name_or_path: str | Path) -> Path:
    """The scenario file meant by a command-line argument: an existing file first (a file in
    the working directory wins over a built-in of the same name), else a built-in name, else a
    ScenarioError listing the built-in names."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    builtin = builtin_scenarios()
    if str(name_or_path) in builtin:
        return builtin[str(name_or_path)].path
    known = ", ".join(builtin) or "none"
    if path.is_dir():
        raise ScenarioError(f"{name_or_path}: is a folder; name a scenario file (.toml) in it")
    raise ScenarioError(
        f"{name_or_path}: no such scenario file or built-in scenario (built-in: {known}; "
        "`hil scenarios` lists them)"
    )


def _robot_section(raw: Any, file: str, key: str) -> Any:
    from hil.rig import robot_kind

    if not isinstance(raw, dict):
        raise _fail(file, key, f"must be a table, got {shown(raw)}")
    kind = raw.get("kind", "planar_arm")
    if not isinstance(kind, str):
        raise _fail(file, f"{key}.kind", f"must be a string, got {shown(kind)}")
    try:
        robot = robot_kind(kind)
    except HilError as exc:
        raise _fail(file, f"{key}.kind", str(exc)) from None
    return _build(robot.spec_class, raw, file, key)


def shown(value: Any) -> str:
    """A value as TOML writes it, for a message: true, 1.5, 'text', a table, an array, or a
    date or time that needs quotes to be the string it was meant as."""
    import datetime as dt

    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dt.datetime):
        text = value.isoformat()
        if value.utcoffset() == dt.timedelta(0):
            text = text.removesuffix("+00:00") + "Z"
        return f"the TOML date-time {text} (quote it)"
    if isinstance(value, dt.date):
        return f"the TOML date {value.isoformat()} (quote it)"
    if isinstance(value, dt.time):
        return f"the TOML time {value.isoformat()} (quote it)"
    return repr(value)


def fail(file: str, key: str, reason: str) -> ScenarioError:
    """The one-line error of a scenario: file, key, reason."""
    return _fail(file, key, reason)


def _fail(file: str, key: str, reason: str) -> ScenarioError:
    return ScenarioError(f"{file}: {key or '(top level)'}: {reason}")


def _build(cls: type, data: Any, file: str, key: str) -> Any:
    if not isinstance(data, dict):
        raise _fail(file, key, f"must be a table, got {shown(data)}")
    hints = typing.get_type_hints(cls)
    if cls is Scenario:
        hints["robot"] = RobotSection
    aliases = _ALIASES.get(cls, {})
    display = {name: raw_name for raw_name, name in aliases.items()}
    known = {f.name: f for f in fields(cls)}
    values: dict[str, Any] = {}
    for raw_name, raw in data.items():
        # a field with a TOML name is known by that name only ("source" in a connection is not)
        name = aliases.get(raw_name, "" if raw_name in display else raw_name)
        sub = f"{key}.{raw_name}" if key else raw_name
        if name not in known:
            names = [display.get(k, k) for k in known if k != "source" or cls is not Scenario]
            allowed = ", ".join(names)
            raise _fail(file, sub, f"unknown key (allowed: {allowed})")
        if raw == [] and name in _NOT_EMPTY.get(cls, {}):
            raise _fail(file, sub, _NOT_EMPTY[cls][name])
        values[name] = _convert(hints[name], raw, file, sub)
    if cls is Scenario and "robot" not in values:
        values["robot"] = _robot_section({}, file, "robot")
    for f in fields(cls):
        if f.name not in values and f.default is MISSING and f.default_factory is MISSING:
            toml_name = display.get(f.name, f.name)
            raise _fail(file, f"{key}.{toml_name}" if key else toml_name, "missing required key")
    return cls(**values)


def _convert(hint: Any, raw: Any, file: str, key: str) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        return _convert(inner[0], raw, file, key)
    if hint is RobotSection:
        return _robot_section(raw, file, key)
    if hint is Any:
        return raw
    if hint is bool:
        if not isinstance(raw, bool):
            raise _fail(file, key, f"must be true or false, got {shown(raw)}")
        return raw
    if hint is float:
        if isinstance(raw, bool) or not isinstance(raw, int | float):
            raise _fail(file, key, f"must be a number, got {shown(raw)}")
        try:
            value = float(raw)
        except OverflowError:
            raise _fail(file, key, "must be finite, got a number too large") from None
        if not math.isfinite(value):
            raise _fail(file, key, f"must be finite, got {shown(raw)}")
        return value
    if hint is bool:
        if not isinstance(raw, bool):
            raise _fail(file, key, f"must be true or false, got {shown(raw)}")
        return raw
    if hint is int:
        if isinstance(raw, bool) or not isinstance(raw, int):
            raise _fail(file, key, f"must be an integer, got {shown(raw)}")
        return raw
    if hint is str:
        if not isinstance(raw, str):
            raise _fail(file, key, f"must be a string, got {shown(raw)}")
        return raw
    if origin is tuple:
        if not isinstance(raw, list):
            raise _fail(file, key, f"must be an array, got {shown(raw)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], item, file, f"{key}[{i}]") for i, item in enumerate(raw))
        if len(raw) != len(args):
            raise _fail(file, key, f"must have {len(args)} elements, got {len(raw)}")
        return tuple(
            _convert(a, item, file, f"{key}[{i}]")
            for i, (a, item) in enumerate(zip(args, raw, strict=True))
        )
    if origin is dict:
        if not isinstance(raw, dict):
            raise _fail(file, key, f"must be a table, got {shown(raw)}")
        return {k: _convert(args[1], v, file, f"{key}.{k}") for k, v in raw.items()}
    if isinstance(hint, type) and hasattr(hint, "__dataclass_fields__"):
        return _build(hint, raw, file, key)
    raise _fail(file, key, f"unsupported type {hint}")  # pragma: no cover - schema bug


def _check(s: Scenario) -> None:
    """Semantic checks: rates, ranges, the robot (its own checks), connections, recording."""
    from hil.rig import robot_kind

    file = s.source
    t = s.timing
    protocol = Protocol()  # the DBC bounds what the bus can carry
    marker_range = protocol.signal_range("CameraMarker0", "x")[1]
    exposure_range = protocol.signal_range("CameraMarker0", "exposure_offset")[1]
    if s.duration <= 0:
        raise _fail(file, "duration", f"must be positive, got {s.duration}")
    if s.seed < 0:
        raise _fail(file, "seed", f"must not be negative, got {s.seed}")
    if not _NAME.fullmatch(s.name):
        raise _fail(
            file,
            "name",
            f"{s.name!r}: use letters, digits, '-', '_' and '.' (it names the results folder)",
        )
    if t.step <= 0 or t.control_period <= 0:
        raise _fail(file, "timing", "step and control_period must be positive")
    _limits(s)
    _multiple(file, "timing.control_period", t.control_period, t.step, "timing.step")
    _multiple(file, "duration", s.duration, t.control_period, "timing.control_period")
    if s.camera.rate <= 0:
        raise _fail(file, "camera.rate", f"must be positive, got {s.camera.rate}")
    _multiple(file, "camera.rate", 1.0 / s.camera.rate, t.step, "timing.step", as_period=True)
    if s.camera.latency < 0:
        raise _fail(file, "camera.latency", "must not be negative")
    _multiple(file, "camera.latency", s.camera.latency, t.step, "timing.step", allow_zero=True)
    try:
        check_effects(s.camera.effects(), 1.0 / s.camera.rate, t.step)
    except ValueError as exc:
        key, _, reason = str(exc).partition(": ")
        raise _fail(file, key, reason) from None
    if s.controller.estimator not in ESTIMATORS:
        raise _fail(
            file,
            "controller.estimator",
            f"unknown estimator {s.controller.estimator!r} (known: {', '.join(ESTIMATORS)})",
        )
    if s.camera.latency + s.timing.control_period > exposure_range:
        raise _fail(
            file,
            "camera.latency",
            f"must be below {exposure_range:g} s less one control "
            "period (the CameraMarker exposure_offset range in the DBC)",
        )
    if s.bus.kind not in BUS_KINDS:
        raise _fail(file, "bus.kind", f"must be one of {', '.join(BUS_KINDS)}")
    if not 0 < s.bus.bitrate <= MAX_BITRATE:
        raise _fail(
            file,
            "bus.bitrate",
            f"must be 1..{MAX_BITRATE} bit/s (classical CAN), got {s.bus.bitrate}",
        )
    if not 0 <= s.bus.port < 65536:
        raise _fail(file, "bus.port", f"must be 0..65535, got {s.bus.port}")
    if s.controller.policy not in POLICIES:
        raise _fail(file, "controller.policy", f"must be one of {', '.join(POLICIES)}")
    if s.controller.timeout <= 0 or s.controller.crossover <= 0:
        raise _fail(file, "controller", "timeout and crossover must be positive")
    if s.controller.torque_std is not None and not s.controller.torque_std > 0:
        raise _fail(
            file, "controller.torque_std", f"must be positive, got {s.controller.torque_std}"
        )
    for gain in ("kp", "ki"):
        value = getattr(s.controller, gain)
        if value is not None and value < 0:
            raise _fail(file, f"controller.{gain}", f"must not be negative, got {value}")
    if s.safety.max_pressure <= 0:
        raise _fail(file, "safety.max_pressure", "must be positive")
    if s.safety.command_timeout < 2 * s.timing.control_period:
        raise _fail(file, "safety.command_timeout", "must be at least two control periods")
    times = [time for time, _ in s.task.steps]
    if any(b <= a for a, b in zip(times, times[1:], strict=False)):
        raise _fail(file, "task.steps", "step times must be strictly increasing")
    if not s.task.scale:
        raise _fail(file, "task.scale", "must not be empty")
    if s.task.sine is not None and s.task.sine.frequency <= 0:
        raise _fail(file, "task.sine.frequency", "must be positive")
    try:
        log_start(s)
    except ValueError as exc:
        raise _fail(file, "recording.start", str(exc)) from None
    problem = can_log_problem(s.recording.can_log)
    if problem is not None:
        raise _fail(file, "recording.can_log", problem)
    robot = robot_kind(s.robot.kind)
    robot.check(s)
    reach = robot.reach(s)
    base = getattr(s.robot, "base", (0.0, 0.0))
    seen = max(abs(base[0]), abs(base[1])) + reach
    if seen > marker_range:
        raise _fail(
            file,
            "robot",
            f"the robot's markers reach {reach:g} m from its base at "
            f"({base[0]:g}, {base[1]:g}): beyond the camera's +-{marker_range:g} m "
            "(the CameraMarker range in the DBC)",
        )
    margin = CAMERA_SIGMAS * s.camera.noise + (
        s.camera.outlier_distance if s.camera.outlier_rate else 0.0
    )
    if seen + margin > marker_range:
        raise _fail(
            file,
            "camera.noise",
            f"{s.camera.noise:g} m: markers up to {seen:g} m from the origin, plus "
            f"{CAMERA_SIGMAS} sigma of noise and the outlier distance ({margin:g} m), leave the "
            f"camera's +-{marker_range:g} m field of view (the CameraMarker range in the DBC)",
        )
    ports = robot.ports(s)
    for i, c in enumerate(s.connections):
        for end, index, kind in (("source", 0, "output"), ("target", 1, "input")):
            value = getattr(c, end)
            key = f"connections[{i}].{'from' if end == 'source' else 'to'}"
            owner, _, variable = value.partition(".")
            if owner not in ports:
                raise _fail(
                    file,
                    key,
                    f"{value!r}: no participant {owner!r} (participants: "
                    f"{', '.join(sorted(ports))})",
                )
            if variable not in ports[owner][index]:
                raise _fail(
                    file,
                    key,
                    f"{value!r}: {owner} has no {kind} {variable!r} "
                    f"({kind}s: {', '.join(sorted(ports[owner][index]))})",
                )


LOG_SUFFIXES = (".log", ".asc", ".blf", ".trc", ".csv", ".mf4")


def can_log_problem(name: str) -> str | None:
    """Why `name` cannot be a run's CAN log (None if it can): it must be a plain file name in the
    results folder, end in a suffix python-can writes, and not be one of softhil's own result
    files (`signals.csv` would be overwritten by the log, and the signals lost)."""
    suffix = Path(name).suffix
    if not _NAME.fullmatch(name) or suffix not in LOG_SUFFIXES:
        return f"{name!r}: a file name (no folder) ending in one of {', '.join(LOG_SUFFIXES)}"
    if is_result_file(name):
        return (
            f"{name!r} is one of softhil's own result files; name the CAN log otherwise "
            f"(e.g. can{suffix})"
        )
    return None


# Bounds of what a run can be asked for (issue 7): a macro step the FMUs' fixed substeps can
# resolve and that does not spin (1 us .. 100 ms), a control period up to 1 s, at most a day of
# simulated time and 10 million SYNCs, so that a typo cannot start a run that never ends.
STEP_RANGE = (1e-6, 0.1)
MAX_CONTROL_PERIOD = 1.0
MAX_DURATION = 86_400.0
MAX_CYCLES = 10_000_000
MAX_TIMEOUT = 3_600.0
# Gains: Kp [m per 1/m] beyond the DBC's whole piston range (0.1 m) per 0.01 1/m of curvature
# error (the camera's resolution over CAN) would only chatter between the stroke's ends; Ki is
# bounded so that one control period integrates at most that much.
CURVATURE_RESOLUTION = 0.01
CAMERA_SIGMAS = 6  # marker noise beyond 6 sigma is vanishingly rare (2e-9)
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")


def _limits(s: Scenario) -> None:
    """The ranges a scenario must keep: timing, duration, bus, gains, pressures, frequencies,
    derived from the physics, the sample rates and the DBC."""
    file, t = s.source, s.timing
    lo, hi = STEP_RANGE
    if not lo <= t.step <= hi:
        raise _fail(file, "timing.step", f"{t.step:g} s is outside {lo:g}..{hi:g} s")
    if t.control_period > MAX_CONTROL_PERIOD:
        raise _fail(
            file,
            "timing.control_period",
            f"{t.control_period:g} s is beyond {MAX_CONTROL_PERIOD:g} s",
        )
    if s.duration > MAX_DURATION:
        raise _fail(file, "duration", f"{s.duration:g} s is beyond {MAX_DURATION:g} s (a day)")
    if s.duration / t.control_period > MAX_CYCLES:
        raise _fail(
            file,
            "duration",
            f"{s.duration / t.control_period:.3g} control periods are beyond {MAX_CYCLES}",
        )
    channel = s.bus.channel
    if not channel or any(c.isspace() or c in "<>" for c in channel):
        raise _fail(file, "bus.channel", f"{channel!r}: no spaces or '<>', not empty")
    if not s.bus.host or any(c.isspace() or c in "<>" for c in s.bus.host):
        raise _fail(file, "bus.host", f"{s.bus.host!r}: not a host name")
    if s.bus.host not in LOOPBACK_HOSTS and not s.bus.allow_remote:
        raise _fail(
            file,
            "bus.host",
            f"{s.bus.host!r}: softhil stays on 127.0.0.1 unless bus.allow_remote = true",
        )
    if not 0.0 < s.controller.timeout <= MAX_TIMEOUT:
        raise _fail(file, "controller.timeout", f"must be in (0, {MAX_TIMEOUT:g}] s")
    if not 0.0 <= s.controller.max_lateness <= MAX_TIMEOUT:
        raise _fail(file, "controller.max_lateness", f"must be in 0..{MAX_TIMEOUT:g} s")
    if not 0.0 <= s.controller.max_overruns <= 1.0:
        raise _fail(file, "controller.max_overruns", "must be a fraction in 0..1")
    if s.controller.crossover > 0.5 / t.control_period:
        raise _fail(
            file,
            "controller.crossover",
            f"{s.controller.crossover:g} Hz is beyond the control loop's Nyquist rate "
            f"{0.5 / t.control_period:g} Hz",
        )
    protocol = Protocol()
    piston = protocol.signal_range("DriveCommand1", "piston_setpoint")
    kp_max = (piston[1] - piston[0]) / CURVATURE_RESOLUTION
    bounds = {"kp": kp_max, "ki": kp_max / t.control_period}
    for gain, bound in bounds.items():
        value = getattr(s.controller, gain)
        if value is not None and value > bound:
            raise _fail(
                file,
                f"controller.{gain}",
                f"{value:g} is beyond {bound:g} (the DBC's whole piston range per "
                f"{CURVATURE_RESOLUTION:g} 1/m of curvature error)",
            )
    pressure = protocol.signal_range("DriveStatus1", "p_a")[1]
    if s.safety.max_pressure > pressure:
        raise _fail(
            file,
            "safety.max_pressure",
            f"{s.safety.max_pressure:g} Pa is beyond the {pressure:g} Pa DriveStatus can carry "
            "(the DBC's p_a range)",
        )
    if s.safety.command_timeout > MAX_TIMEOUT:
        raise _fail(file, "safety.command_timeout", f"must be at most {MAX_TIMEOUT:g} s")
    sine = s.task.sine
    if sine is not None and s.camera.rate > 0:
        nyquist = min(0.5 / t.control_period, 0.5 * s.camera.rate)
        if sine.frequency >= nyquist:
            raise _fail(
                file,
                "task.sine.frequency",
                f"{sine.frequency:g} Hz is at or beyond the Nyquist rate {nyquist:g} Hz of the "
                "control loop and camera",
            )


def log_start(s: Scenario) -> float:
    """The CAN log's start instant [s since the epoch, UTC]; ValueError if unreadable."""
    import datetime as dt
    import time as wall

    text = s.recording.start
    if text == "now":
        return round(wall.time(), 6)
    try:
        instant = dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(
            f"{text!r} is not an ISO 8601 instant (e.g. 2015-06-01T00:00:00Z) or 'now'"
        ) from None
    if instant.tzinfo is None:
        instant = instant.replace(tzinfo=dt.UTC)
    start = instant.timestamp()
    if start < 0:  # a CAN log stamps seconds since the epoch; candump and BLF take no sign
        raise ValueError(f"{text!r} is before 1970-01-01T00:00:00Z, the CAN log stamps' epoch")
    last = dt.datetime(9999, 12, 31, 23, 59, 59, tzinfo=dt.UTC).timestamp()
    if start + s.duration > last:  # every frame's stamp must be a date the log formats write
        raise ValueError(
            f"{text!r}: the run would end after 9999-12-31T23:59:59Z, a year the log formats "
            "(.blf, .asc) cannot write"
        )
    return start


def _multiple(
    file: str,
    key: str,
    value: float,
    unit: float,
    unit_key: str,
    *,
    as_period: bool = False,
    allow_zero: bool = False,
) -> None:
    ratio = value / unit
    n = round(ratio)
    if abs(ratio - n) > 1e-9 * max(1.0, ratio) or (n < 1 and not allow_zero):
        what = f"period {value:g} s" if as_period else f"{value:g} s"
        raise _fail(file, key, f"{what} is not an integer multiple of {unit_key} = {unit:g} s")


@dataclass(frozen=True)
class Port:
    causality: str
    start: float | None
    min: float | None
    max: float | None


def fmu_interface(file: str, key: str, fmu: str) -> dict[str, Port]:
    """The variables of a softhil model (from model.toml) or of an external .fmu file."""
    from hil.fmu.build import model_folder
    from hil.fmu.spec import load_spec

    if fmu.endswith(".fmu"):
        path = fmu_path(file, fmu)
        if not path.is_file():
            raise _fail(file, key, f"FMU file {str(path)!r} does not exist")
        try:
            from fmpy import read_model_description

            description = read_model_description(str(path))
        except Exception as exc:  # fmpy raises zipfile, XML and its own errors
            raise _fail(file, key, f"{path}: not a readable FMU: {exc}") from None
        return {
            v.name: Port(v.causality, _number(v.start), _number(v.min), _number(v.max))
            for v in description.modelVariables
        }
    try:
        spec = load_spec(model_folder(fmu))
    except HilError as exc:
        raise _fail(file, key, str(exc)) from None
    return {v.name: Port(v.causality, v.start, v.min, v.max) for v in spec.variables}


def fmu_path(file: str, fmu: str) -> Path:
    """An .fmu named in a scenario, relative to the scenario file."""
    path = Path(fmu)
    return path if path.is_absolute() else Path(file).parent / path


def _number(value: object) -> float | None:
    try:
        return None if value is None else float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None


def check_parameter(
    file: str, key: str, interface: dict[str, Port], name: str, value: float
) -> None:
    port = interface.get(name)
    if port is None or port.causality != "parameter":
        known = ", ".join(n for n, p in interface.items() if p.causality == "parameter")
        raise _fail(file, key, f"no such parameter (parameters: {known})")
    if (port.min is not None and value < port.min) or (port.max is not None and value > port.max):
        lo = "-inf" if port.min is None else f"{port.min:g}"
        hi = "inf" if port.max is None else f"{port.max:g}"
        raise _fail(file, key, f"{value:g} is outside the allowed range [{lo}, {hi}]")
