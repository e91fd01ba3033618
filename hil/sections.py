"""The scenario's sections as data: each a frozen dataclass whose keys are declared once with
`hil.schema.setting` (type, unit, range, default, description) and whose `RULES` relate keys
(hil.schema). `hil.scenario.Scenario` holds them; `hil scenarios --keys` lists every key.

Invariant: a bound here is a physical or protocol limit with its source (the DBC, classical
CAN, the sample rates), never a guess; what cannot be said as a bound or a rule is code in
`hil.scenario` or the robot kind.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from hil.results import is_result_file
from hil.schema import (
    Check,
    Computed,
    Context,
    Dbc,
    Is,
    Multiple,
    Needs,
    OneOf,
    Pattern,
    Range,
    Ref,
    Rule,
    fraction,
    not_negative,
    positive,
    setting,
)
from hil.seam import ESTIMATORS, POLICIES, CurvatureProfile, Sine
from hil.vision import SCOPES, CameraEffects
from rigbus.canbus import KINDS as BUS_KINDS
from rigbus.canbus import OUR_KINDS

if TYPE_CHECKING:
    from hil.scenario import Scenario

# [bit/s] classical CAN (ISO 11898-1) runs at most 1 Mbit/s; softhil's frames are classical, so
# the bus load and frame times are computed at one bitrate
MAX_BITRATE = 1_000_000
DEFAULT_LOG_START = "2015-06-01T00:00:00Z"  # the thesis's year; see RecordingSpec
NAME = Pattern(r"[A-Za-z0-9_.-]+", "use letters, digits, '-', '_' and '.'")
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
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
HOST = Pattern(r"[^\s<>]+", "be a host name (no spaces or '<>')")


def _kp_max(ctx: Context) -> float:
    low, high = ctx.protocol.signal_range("DriveCommand1", "piston_setpoint")
    return (high - low) / CURVATURE_RESOLUTION


def _ki_max(ctx: Context) -> float | None:
    period = ctx.value("timing.control_period")
    return _kp_max(ctx) / period if period else None


def _exposure_bound(ctx: Context) -> float:
    exposure = ctx.protocol.signal_range("CameraMarker0", "exposure_offset")[1]
    return float(exposure - ctx.value("timing.control_period"))


GAIN_WHY = f"the DBC's whole piston range per {CURVATURE_RESOLUTION:g} 1/m of curvature error"


@dataclass(frozen=True)
class TimingSpec:
    step: float = setting(1e-3, "s", "the plant's macro step h", Range(*STEP_RANGE))
    control_period: float = setting(
        1e-2,
        "s",
        "the SYNC period T: an integer multiple of timing.step",
        Range(0, MAX_CONTROL_PERIOD, lo_open=True),
    )

    RULES: ClassVar[tuple[Rule, ...]] = (Multiple("timing.control_period", "timing.step"),)


def _log_start_problem(text: str, ctx: Context) -> str | None:
    try:
        log_start(ctx.root)
    except ValueError as exc:
        return str(exc)
    return None


@dataclass(frozen=True)
class RecordingSpec:
    """What a run records and how its logs are stamped."""

    # the default is fixed so that reruns give byte-identical logs
    start: str = setting(
        DEFAULT_LOG_START,
        doc='the CAN log\'s first stamp (ISO 8601), simulation time added; "now": the wall clock',
    )
    can_log: str = setting(
        "can.log", doc="the CAN log's file name in the results folder; its suffix picks its format"
    )
    mf4: bool = setting(False, doc="also write the signals as MF4 (needs asammdf)")

    RULES: ClassVar[tuple[Rule, ...]] = (
        Check(
            "recording.start",
            _log_start_problem,
            "must be an ISO 8601 instant from 1970 on (the run ending by 9999), or now",
        ),
        Check(
            "recording.can_log",
            lambda name, ctx: can_log_problem(name),
            "must be a file name (no folder) ending in a suffix python-can writes, and no result "
            "file's",
        ),
    )


@dataclass(frozen=True)
class ConnectionSpec:
    source: str = setting(doc="participant.variable the value comes from", toml="from")
    target: str = setting(
        doc="participant.variable it drives (replaces a default there)", toml="to"
    )
    gain: float = setting(1.0, doc="target = gain * source + offset")
    offset: float = setting(0.0, doc="target = gain * source + offset")


@dataclass(frozen=True)
class BusConfig:
    kind: str = setting(
        "loopback",
        doc="the CAN transport",
        choices=OneOf(BUS_KINDS, summary=", ".join(OUR_KINDS) + " or a python-can interface"),
    )
    channel: str = setting(
        "softhil",
        doc="the bus's channel",
        pattern=Pattern(r"[^\s<>]+", "be a name without spaces or '<>', not empty"),
    )
    host: str = setting("127.0.0.1", doc="the hub's host", pattern=HOST)
    port: int = setting(
        0,
        doc="the hub's TCP port (0: `hil run` serves its own hub on a free port)",
        range=Range(0, 65535),
    )
    bitrate: int = setting(
        1_000_000,
        "bit/s",
        "the bitrate the bus load and frame times are computed at",
        Range(1, MAX_BITRATE, why="classical CAN"),
    )
    allow_remote: bool = setting(
        False, doc="allow a host beyond the loopback (0.0.0.0, another machine)"
    )

    RULES: ClassVar[tuple[Rule, ...]] = (
        Needs(
            "bus.host",
            OneOf(LOOPBACK_HOSTS),
            unless=("bus.allow_remote", Is(True)),
            why="softhil stays on the loopback unless told",
        ),
    )


@dataclass(frozen=True)
class CameraSpec:
    """The camera (hil/vision.py): SI units, 0 switches an effect off. The defaults are a
    realistic commercial motion-capture system, not an ideal camera."""

    rate: float = setting(100.0, "Hz", "frames per second", positive())
    latency: float = setting(0.006, "s", "from exposure to availability", not_negative())
    noise: float = setting(
        0.5e-3, "m", "isotropic marker position standard deviation", not_negative()
    )
    dropout: float = setting(0.01, "", "per-marker probability of a missing marker", fraction())
    occlusion_interval: float = setting(
        0.0, "s", "mean time between occlusion bursts (0: none)", not_negative()
    )
    occlusion_duration: float = setting(0.0, "s", "an occlusion burst's length", not_negative())
    occlusion_scope: str = setting(
        "frame", doc='what a burst hides: the whole "frame" or one "marker"', choices=SCOPES
    )
    outlier_rate: float = setting(
        0.001, "", "per-marker probability of a displaced marker", fraction()
    )
    outlier_distance: float = setting(0.02, "m", "an outlier's displacement", not_negative())
    jitter: float = setting(
        0.0,
        "s",
        "exposure-time jitter standard deviation",
        Range(
            0, Ref("camera.rate", per=True), hi_open=True, why="the frame period 1 / camera.rate"
        ),
    )

    RULES: ClassVar[tuple[Rule, ...]] = (
        Multiple("camera.rate", "timing.step", as_period=True),
        Multiple("camera.latency", "timing.step", allow_zero=True),
        Needs(
            "camera.latency",
            Range(
                hi=Computed(
                    "the DBC's CameraMarker exposure_offset range less one control period",
                    _exposure_bound,
                    ("timing.control_period",),
                ),
                hi_open=True,
            ),
            unit="s",
        ),
        Needs(
            "camera.occlusion_duration", positive(), when=("camera.occlusion_interval", positive())
        ),
        Needs("camera.outlier_distance", positive(), when=("camera.outlier_rate", positive())),
    )

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
    max_pressure: float = setting(
        60e3,
        "Pa",
        "gauge pressure beyond which the drive holds and sends EMCY",
        Range(0, Dbc("DriveStatus1", "p_a"), lo_open=True),
    )
    command_timeout: float = setting(
        0.1,
        "s",
        "time without a command before the drive holds and sends EMCY",
        Range(Ref("timing.control_period", 2), MAX_TIMEOUT, why="at least two control periods"),
    )


NYQUIST = Ref("timing.control_period", 0.5, per=True)


@dataclass(frozen=True)
class ControllerSpec:
    kp: float | None = setting(
        None,
        "m per 1/m",
        "proportional gain (absent: designed from the segment physics)",
        not_negative(),
    )
    ki: float | None = setting(
        None, "m per (1/m) s", "integral gain (absent: designed)", not_negative()
    )
    crossover: float = setting(
        1.0,
        "Hz",
        "crossover of the designed gains",
        Range(0, NYQUIST, lo_open=True, why="the control loop's Nyquist rate"),
    )
    feedforward: bool = setting(
        True, doc="static inverse of the segment's curvature per piston travel"
    )
    policy: str = setting("strict", doc="what the controller does on a fault", choices=POLICIES)
    timeout: float = setting(
        10.0, "s", "wall-clock wait for a peer", Range(0, MAX_TIMEOUT, lo_open=True)
    )
    estimator: str = setting(
        "ukf", doc="the curvature estimator (ukf measures best on the default)", choices=ESTIMATORS
    )
    latency_compensation: bool = setting(True, doc="fuse camera frames at their exposure time")
    # None: derived per segment from table friction and pressure quantisation (a held object's
    # load needs more)
    torque_std: float | None = setting(
        None,
        "N m",
        "the estimator's unmodelled torque standard deviation (absent: derived per segment)",
        positive(),
    )
    # real-time runs fail when a SYNC is later than max_lateness (0: one control period), or
    # when more than the fraction max_overruns of SYNCs is over one control period late
    max_lateness: float = setting(
        0.0,
        "s",
        "real time: the latest a SYNC may be (0: one control period)",
        Range(0, MAX_TIMEOUT),
    )
    max_overruns: float = setting(
        0.01,
        "",
        "real time: the share of SYNCs that may be over a control period late",
        fraction(),
    )

    RULES: ClassVar[tuple[Rule, ...]] = (
        Needs("controller.kp", Range(hi=Computed(GAIN_WHY, _kp_max)), unit="m per 1/m"),
        Needs(
            "controller.ki",
            Range(
                hi=Computed(GAIN_WHY + " per control period", _ki_max, ("timing.control_period",))
            ),
            unit="m per (1/m) s",
        ),
    )


@dataclass(frozen=True)
class SineSpec:
    """A curvature sine a curvature_profile adds to its steps from its start on."""

    start: float = setting(unit="s", doc="when the sine starts")
    amplitude: float = setting(unit="1/m", doc="curvature amplitude")
    frequency: float = setting(
        unit="Hz",
        doc="below the control loop's and the camera's Nyquist rates",
        range=Range(0, NYQUIST, lo_open=True, hi_open=True, why="the control loop's Nyquist rate"),
    )
    offset: float = setting(0.0, "1/m", "curvature offset")

    RULES: ClassVar[tuple[Rule, ...]] = (
        Needs(
            "task.sine.frequency",
            Range(hi=Ref("camera.rate", 0.5), hi_open=True, why="the camera's Nyquist rate"),
            unit="Hz",
        ),
    )


def _increasing(steps: tuple[tuple[float, float], ...], ctx: Context) -> str | None:
    times = [time for time, _ in steps]
    if any(b <= a for a, b in zip(times, times[1:], strict=False)):
        return "step times must be strictly increasing"
    return None


@dataclass(frozen=True)
class TaskSpec:
    """The task: a curvature profile per segment (`curvature_profile`), or in task space
    (`point_to_point`, `path`, `pipe`, `grasp`: README, "Task space"); the robot kind says which
    kinds it takes. Lengths in m, times in s."""

    kind: str = setting(
        "curvature_profile",
        doc="the task, one of the robot kind's (the arm: curvature_profile, point_to_point, "
        "path, pipe, grasp; the fish: escape, swim, heading)",
    )
    steps: tuple[tuple[float, float], ...] = setting(
        (), "s, 1/m", "curvature_profile: steps [time, curvature], times increasing"
    )
    sine: SineSpec | None = setting(None, doc="curvature_profile: a sine added to the steps")
    scale: tuple[float, ...] = setting(
        (1.0,),
        "",
        "curvature_profile: the profile's factor per segment (repeated)",
        not_empty="",
    )
    # task space: targets [x, y] or paths [x0, y0, x1, y1]; empty: `count` drawn from the seed
    targets: tuple[tuple[float, float], ...] = setting(
        (),
        "m",
        "point_to_point: targets [x, y] (absent: task.count drawn from the seed)",
        not_empty="leave it out to draw task.count targets from the seed",
    )
    paths: tuple[tuple[float, float, float, float], ...] = setting(
        (),
        "m",
        "path: paths [x0, y0, x1, y1] (absent: task.count drawn from the seed)",
        not_empty="leave it out to draw task.count paths from the seed",
    )
    count: int = setting(8, "", "targets or paths drawn from the seed", Range(1, 65535))
    margin: float = setting(
        0.7,
        "",
        "share of each segment's reachable curvature range drawn targets use",
        Range(0, 1, lo_open=True),
    )
    path_length: float = setting(0.08, "m", "drawn paths' length", positive())
    tolerance: float = setting(1e-3, "m", "the estimated tip within it: on target", positive())
    settle_time: float = setting(
        0.5,
        "s",
        "on target this long: settled, next target",
        Range(0, Ref("task.max_time"), lo_open=True, hi_open=True),
    )
    max_time: float = setting(
        6.0, "s", "per target, before the controller gives up on it", positive()
    )
    speed: float = setting(0.01, "m/s", "path speed", positive())
    acceleration: float = setting(0.02, "m/s^2", "path acceleration", positive())
    task_gain: float = setting(
        1.0,
        "1/s",
        "integral gain on the estimated tip error",
        Range(
            0,
            Ref("timing.control_period", per=True),
            hi_open=True,
            why="its product with timing.control_period stays below 1",
        ),
    )
    band: float = setting(2e-3, "m", "settling band of the time_to_settle metric", positive())
    # confined spaces (kind "pipe"): the goal deep in the channel of [robot.environment] walls,
    # the centreline the tip follows, and the clearance the plan keeps beyond the arm's width
    goal: tuple[float, float] | None = setting(
        None, "m", "pipe: the goal [x, y] deep in the channel"
    )
    centreline: tuple[tuple[float, float], ...] = setting(
        (), "m", "pipe: the channel's centreline the tip follows, [x, y] points"
    )
    clearance: float = setting(
        2e-3, "m", "pipe: the clearance the plan keeps beyond the arm's width", not_negative()
    )
    # grasp-and-place (kind "grasp"): where the object starts (`pick`) and where it goes
    # (`place`), each drawn from the seed unless given; the fingers' closing and opening time
    pick: tuple[float, float] | None = setting(
        None, "m", "grasp: where the object starts [x, y] (absent: drawn from the seed)"
    )
    place: tuple[float, float] | None = setting(
        None, "m", "grasp: where the object goes [x, y] (absent: drawn from the seed)"
    )
    grasp_time: float = setting(
        1.0, "s", "grasp: the fingers' closing and opening time", positive()
    )

    RULES: ClassVar[tuple[Rule, ...]] = (
        Check("task.steps", _increasing, "must have strictly increasing step times"),
    )

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


LOG_SUFFIXES = (".log", ".asc", ".blf", ".trc", ".csv", ".mf4")


def can_log_problem(name: str) -> str | None:
    """Why `name` cannot be a run's CAN log (None if it can): it must be a plain file name in the
    results folder, end in a suffix python-can writes, and not be one of softhil's own result
    files (`signals.csv` would be overwritten by the log, and the signals lost)."""
    suffix = Path(name).suffix
    if not NAME.holds(name) or suffix not in LOG_SUFFIXES:
        return f"{name!r}: a file name (no folder) ending in one of {', '.join(LOG_SUFFIXES)}"
    if is_result_file(name):
        return (
            f"{name!r} is one of softhil's own result files; name the CAN log otherwise "
            f"(e.g. can{suffix})"
        )
    return None


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
