"""Scenarios: TOML files that say what to run, validated completely before anything runs.

A scenario names the robot (its FMUs and parameters), extra connections, rates, bus, camera,
safety limits, controller and task, seed and duration. Each section is a frozen dataclass whose
keys are declared once with `hil.schema.setting` (type, unit, range, default, description) and
whose `RULES` relate keys; `hil scenarios --keys` lists them all (docs/scenario-keys.md).
`load_scenario` returns a frozen `Scenario` or raises `ScenarioError` with one line naming the
file, the key and the reason, generated from the declaration that failed; what is truly code
(the camera's field of view, the connections' ports, the robot kind's own checks) follows the
declared checks. The built-in scenarios ship with the robot kinds: every
`robots/<kind>/scenarios/*.toml`,
named by its file stem (`builtin_scenarios`, `resolve_scenario`); `default` is the one `hil run`
runs.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, replace
from importlib.resources import files
from pathlib import Path
from typing import Any, ClassVar

from hil.errors import HilError, ScenarioError
from hil.schema import (
    INTERNAL,
    Context,
    Multiple,
    Needs,
    Range,
    Ref,
    RobotSection,
    Rule,
    build,
    check,
    fail,
    not_negative,
    setting,
)
from hil.sections import MAX_BITRATE as MAX_BITRATE  # read here by hil.bustools
from hil.sections import (
    MAX_CYCLES,
    MAX_DURATION,
    NAME,
    BusConfig,
    CameraSpec,
    ConnectionSpec,
    ControllerSpec,
    RecordingSpec,
    SafetySpec,
    TaskSpec,
    TimingSpec,
)
from hil.sections import can_log_problem as can_log_problem  # and by hil.run
from hil.sections import log_start as log_start  # and by hil.run

# the built-in scenarios: each robot kind's folder of them
SCENARIO_FOLDERS = tuple(sorted(Path(str(files("robots"))).glob("*/scenarios")))
DEFAULT_SCENARIO = Path(str(files("robots"))) / "planar_arm" / "scenarios" / "default.toml"
CAMERA_SIGMAS = 6  # marker noise beyond 6 sigma is vanishingly rare (2e-9)


@dataclass(frozen=True)
class Scenario:
    name: str = setting(
        doc="the scenario's name",
        pattern=replace(NAME, says=NAME.says + " (it names the results folder)"),
    )
    seed: int = setting(doc="seeds every random draw of the run", range=not_negative())
    duration: float = setting(
        unit="s",
        doc="simulated time, an integer multiple of timing.control_period",
        range=Range(0, MAX_DURATION, lo_open=True, why="a day"),
    )
    description: str = setting("", doc="one line, shown by `hil scenarios`")
    timing: TimingSpec = setting(TimingSpec(), doc="the plant's step and the control period")
    robot: Any = setting(None, doc="the robot: its kind and that kind's keys", hint=RobotSection)
    connections: tuple[ConnectionSpec, ...] = setting(
        (), doc="connections beyond the robot's own ([[connections]])"
    )
    bus: BusConfig = setting(BusConfig(), doc="the CAN bus")
    camera: CameraSpec = setting(CameraSpec(), doc="the camera")
    safety: SafetySpec = setting(SafetySpec(), doc="the drives' safety limits")
    controller: ControllerSpec = setting(ControllerSpec(), doc="the controller")
    task: TaskSpec = setting(TaskSpec(), doc="the task")
    recording: RecordingSpec = setting(RecordingSpec(), doc="what a run records")
    source: str = setting("<built-in>", doc=INTERNAL)

    RULES: ClassVar[tuple[Rule, ...]] = (
        Multiple("duration", "timing.control_period"),
        Needs(
            "duration",
            Range(hi=Ref("timing.control_period", MAX_CYCLES), why=f"{MAX_CYCLES} control periods"),
            unit="s",
        ),
    )

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
    scenario = replace(build(Scenario, data, str(source), ""), source=str(source))
    if seed is not None:
        if seed < 0:
            raise ScenarioError(f"--seed: must not be negative, got {seed}")
        scenario = replace(scenario, seed=seed)
    _check(scenario)
    return scenario


def _check(s: Scenario) -> None:
    """Every declared key and rule (hil.schema), the robot kind's declared keys and its own
    checks, then what is code here: the camera's field of view and the connections."""
    from hil.rig import robot_kind

    ctx = Context(s, s.source)
    check(s, "", ctx)
    robot = robot_kind(s.robot.kind)
    check(s.robot, "robot", ctx)
    robot.check(s)
    _field_of_view(s, robot.reach(s), ctx)
    _connections(s, robot.ports(s))


def _field_of_view(s: Scenario, reach: float, ctx: Context) -> None:
    """Every marker within the camera's range in the DBC, with a margin for its noise and
    outliers."""
    marker_range = ctx.protocol.signal_range("CameraMarker0", "x")[1]
    base = getattr(s.robot, "base", (0.0, 0.0))
    seen = max(abs(base[0]), abs(base[1])) + reach
    if seen > marker_range:
        raise fail(
            s.source,
            "robot",
            f"the robot's markers reach {reach:g} m from its base at "
            f"({base[0]:g}, {base[1]:g}): beyond the camera's +-{marker_range:g} m "
            "(the CameraMarker range in the DBC)",
        )
    margin = CAMERA_SIGMAS * s.camera.noise + (
        s.camera.outlier_distance if s.camera.outlier_rate else 0.0
    )
    if seen + margin > marker_range:
        raise fail(
            s.source,
            "camera.noise",
            f"{s.camera.noise:g} m: markers up to {seen:g} m from the origin, plus "
            f"{CAMERA_SIGMAS} sigma of noise and the outlier distance ({margin:g} m), leave the "
            f"camera's +-{marker_range:g} m field of view (the CameraMarker range in the DBC)",
        )


def _connections(s: Scenario, ports: dict[str, tuple[set[str], set[str]]]) -> None:
    """Each connection's ends: a participant's output and a participant's input."""
    for i, c in enumerate(s.connections):
        for end, index, kind in (("source", 0, "output"), ("target", 1, "input")):
            value = getattr(c, end)
            key = f"connections[{i}].{'from' if end == 'source' else 'to'}"
            owner, _, variable = value.partition(".")
            if owner not in ports:
                raise fail(
                    s.source,
                    key,
                    f"{value!r}: no participant {owner!r} (participants: "
                    f"{', '.join(sorted(ports))})",
                )
            if variable not in ports[owner][index]:
                raise fail(
                    s.source,
                    key,
                    f"{value!r}: {owner} has no {kind} {variable!r} "
                    f"({kind}s: {', '.join(sorted(ports[owner][index]))})",
                )


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
            raise fail(file, key, f"FMU file {str(path)!r} does not exist")
        try:
            from fmpy import read_model_description

            description = read_model_description(str(path))
        except Exception as exc:  # fmpy raises zipfile, XML and its own errors
            raise fail(file, key, f"{path}: not a readable FMU: {exc}") from None
        return {
            v.name: Port(v.causality, _number(v.start), _number(v.min), _number(v.max))
            for v in description.modelVariables
        }
    try:
        spec = load_spec(model_folder(fmu))
    except HilError as exc:
        raise fail(file, key, str(exc)) from None
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
        raise fail(file, key, f"no such parameter (parameters: {known})")
    if (port.min is not None and value < port.min) or (port.max is not None and value > port.max):
        lo = "-inf" if port.min is None else f"{port.min:g}"
        hi = "inf" if port.max is None else f"{port.max:g}"
        raise fail(file, key, f"{value:g} is outside the allowed range [{lo}, {hi}]")
