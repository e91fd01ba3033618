"""The planar arm's world (issue 12): `[robot.environment]` to the Environment FMU.

    [robot.environment]
    walls = [[[x, y], [x, y], ...], [[x, y], ...]]      # up to 2 polylines (channel walls) [m]
    objects = [{ x = 0.2, y = 0.1, radius = 0.015, mass = 0.01, mu = 0.3 }]   # up to 4 disks
    width = 0.016                 # backbone width [m] or a list (default: the actuator's)
    k_contact = 1000.0                                   # any other Environment parameter

When the section is present the robot adds one Environment FMU: each segment's curvature and
bend rate go in, each segment's external torque (`tau_ext`, work-conjugate to its bend angle)
comes back, so contact and table friction act on the simulated arm. The coupling's arm mobility
is the segments' 1 / d_bend (the FMU's implicit coupling needs at least that: fmus/Environment).
Invariant: every key is checked against the FMU's own capacity and ranges before a run starts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from hil.rig import SignalSpec
from hil.schema import Key, Table

if TYPE_CHECKING:
    from hil.scenario import Scenario

FMU = "Environment"
MAX_WALLS, MAX_VERTICES, MAX_OBJECTS, MAX_SEGMENTS = 2, 16, 4, 7
# parameters a scenario may set directly (the rest come from the arm or the keys below)
SETTABLE = (
    "n_samples",
    "k_contact",
    "d_contact",
    "mu_arm",
    "mu_table",
    "mu_table_object",
    "v_slip",
    "gravity",
    "coupling_delay",
    "substep",
)
TABLE = Table(
    "robot.environment",
    (
        Key(
            "walls",
            tuple[tuple[tuple[float, float], ...], ...],
            (),
            "m",
            f"up to {MAX_WALLS} polylines of 2..{MAX_VERTICES} [x, y] vertices (channel walls)",
        ),
        Key(
            "objects",
            tuple[dict[str, float], ...],
            (),
            "",
            f"up to {MAX_OBJECTS} disks on the table (robot.environment.objects[i])",
        ),
        Key(
            "width",
            float | tuple[float, ...],
            None,
            "m",
            "the backbone's width for contact, or one per segment (absent: the actuator's)",
        ),
    ),
    others="the Environment FMU's parameters " + ", ".join(SETTABLE),
    fmu=FMU,
    checked=False,
    doc="the arm's world: contact with walls and objects, table friction",
    settable=SETTABLE,
)
# an object's keys, each checked against the Environment FMU's range for it (its parameter)
OBJECT = Table(
    "robot.environment.objects[i]",
    (
        Key("x", float, None, "m", "where it starts (absent: placed by a grasp task)"),
        Key("y", float, None, "m", "where it starts (absent: placed by a grasp task)"),
        Key("radius", float, 0.015, "m", "the disk's radius"),
        Key("mass", float, 0.01, "kg", "its mass"),
        Key("mu", float, 0.3, "", "its friction coefficient against the arm"),
        Key("yaw", float, 0.0, "rad", "its start heading"),
        Key("height", float, 0.05, "m", "its height (it tips over beyond its base)"),
    ),
    checked=False,
    doc="one disk of robot.environment.objects; each value within the Environment FMU's range "
    "of its parameter (x: object_x0_N, yaw: object_yaw0_N, radius: object_radius_N, ...)",
)
OBJECT_KEYS = {key.name: key.default for key in OBJECT.keys}


def present(scenario: Scenario) -> bool:
    return bool(getattr(scenario.robot, "environment", {}))


def parameters(
    scenario: Scenario,
    segments: Sequence[Mapping[str, float]],
    width: float,
    placed: Mapping[int, tuple[float, float]] | None = None,
) -> dict[str, float]:
    """The Environment FMU's parameters from `[robot.environment]` and the arm's segments;
    raises ScenarioError naming the key. `placed` gives the positions of objects (by 1-based
    index) that the task places (a grasp task draws its object's position from the seed)."""
    from hil.scenario import check_parameter, fail, fmu_interface

    file = scenario.source
    raw: dict[str, Any] = dict(scenario.robot.environment)
    n = len(segments)
    if n > MAX_SEGMENTS:
        raise fail(
            file,
            "robot.environment",
            f"the Environment FMU carries at most {MAX_SEGMENTS} segments",
        )
    interface = fmu_interface(file, "robot.environment", FMU)
    values = _arm(scenario, segments, raw.get("width", width))
    values.update(_walls(file, raw.get("walls", [])))
    values.update(_objects(scenario, placed or {}))
    for name, value in raw.items():
        if name in TABLE_KEYS:
            continue
        key = f"robot.environment.{name}"
        number = _number(file, key, value)
        if name in values or name not in SETTABLE:
            raise fail(file, key, "set by the robot, not by the scenario")
        values[name] = number
    for name, value in values.items():
        key = f"robot.environment.{name}" if name in raw else f"robot.environment ({name})"
        check_parameter(file, key, interface, name, value)
    return values


TABLE_KEYS = tuple(key.name for key in TABLE.keys)


def _arm(
    scenario: Scenario, segments: Sequence[Mapping[str, float]], width: Any
) -> dict[str, float]:
    """The arm's parameters: its base, each segment's length, mass and width, its mobility."""
    n = len(segments)
    base = scenario.robot.base
    values: dict[str, float] = {"n_segments": float(n)}
    values.update(base_x=base[0], base_y=base[1], base_heading=base[2])
    widths = _per_segment(scenario.source, "robot.environment.width", width, n)
    for i, segment in enumerate(segments, start=1):
        values[f"length_{i}"] = segment["length"]
        values[f"mass_{i}"] = segment["mass"]
        values[f"width_{i}"] = widths[i - 1]
    # the implicit coupling predicts the arm with its mobility: at least the most mobile segment's
    values["arm_mobility"] = max(1.0 / max(s["d_bend"], 1e-12) for s in segments)
    return values


def _walls(file: str, walls: Any) -> dict[str, float]:
    """The walls' parameters: how many, and each one's vertices."""
    from hil.scenario import fail

    if not isinstance(walls, list) or len(walls) > MAX_WALLS:
        raise fail(file, "robot.environment.walls", f"a list of at most {MAX_WALLS} polylines")
    values = {"n_walls": float(len(walls))}
    for w, wall in enumerate(walls, start=1):
        key = f"robot.environment.walls[{w - 1}]"
        if not isinstance(wall, list) or not 2 <= len(wall) <= MAX_VERTICES:
            raise fail(file, key, f"a polyline of 2..{MAX_VERTICES} [x, y] vertices")
        values[f"wall{w}_n"] = float(len(wall))
        for v, vertex in enumerate(wall, start=1):
            x, y = _point(file, f"{key}[{v - 1}]", vertex)
            values[f"wall{w}_x_{v}"], values[f"wall{w}_y_{v}"] = x, y
    return values


def _objects(scenario: Scenario, placed: Mapping[int, tuple[float, float]]) -> dict[str, float]:
    """The objects' parameters: how many, and each one's keys (a placed one's position from
    `placed`)."""
    from hil.scenario import fail

    items = objects(scenario)
    values = {"n_objects": float(len(items))}
    for o, item in enumerate(items, start=1):
        key = f"robot.environment.objects[{o - 1}]"
        for name, value in item.items():
            if o in placed and name in ("x", "y"):
                if value is not None:
                    raise fail(scenario.source, f"{key}.{name}", "placed by the task: leave it out")
                value = placed[o][0 if name == "x" else 1]
            if value is None:
                raise fail(scenario.source, f"{key}.{name}", "missing required key")
            values[_object_parameter(name, o)] = value
    return values


def objects(scenario: Scenario) -> list[dict[str, float | None]]:
    """`[robot.environment] objects`, each a table of OBJECT_KEYS with the defaults filled in
    (x and y None where not given: a task may place them), every value a finite number within
    the Environment FMU's range; raises ScenarioError naming the key, such as
    `robot.environment.objects[0].radius`, before anything (a grasp task's draw, the camera's
    markers) uses them."""
    from hil.scenario import check_parameter, fail, fmu_interface

    file = scenario.source
    raw = scenario.robot.environment.get("objects", [])
    if not isinstance(raw, list) or len(raw) > MAX_OBJECTS:
        raise fail(
            file,
            "robot.environment.objects",
            f"must be a list of at most {MAX_OBJECTS} tables, got {raw!r}",
        )
    interface = fmu_interface(file, "robot.environment", FMU)
    items = []
    for o, item in enumerate(raw, start=1):
        key = f"robot.environment.objects[{o - 1}]"
        if not isinstance(item, dict):
            raise fail(file, key, "a table {x, y, radius, mass, mu, yaw, height}")
        unknown = set(item) - set(OBJECT_KEYS)
        if unknown:
            raise fail(
                file,
                f"{key}.{sorted(unknown)[0]}",
                f"unknown key (allowed: {', '.join(OBJECT_KEYS)})",
            )
        checked: dict[str, float | None] = {}
        for name, default in OBJECT_KEYS.items():
            value = item.get(name, default)
            if value is not None:
                value = _number(file, f"{key}.{name}", value)
                check_parameter(file, f"{key}.{name}", interface, _object_parameter(name, o), value)
            checked[name] = value
        items.append(checked)
    return items


def _object_parameter(name: str, o: int) -> str:
    """The Environment FMU's parameter for key `name` of object `o` (1-based)."""
    stem = {"x": "object_x0", "y": "object_y0", "yaw": "object_yaw0"}.get(name, f"object_{name}")
    return f"{stem}_{o}"


def connections(ports: Sequence[Mapping[str, str]]) -> list[tuple[str, str]]:
    """Each segment's signed curvature and bend rate in, its external torque out; `ports[n - 1]`
    names segment n's (kappa, theta_dot, tau_ext: on its FeaSegment or on the arm body)."""
    pairs = []
    for n, port in enumerate(ports, start=1):
        pairs += [
            (port["kappa"], f"environment.kappa_{n}"),
            (port["theta_dot"], f"environment.theta_dot_{n}"),
            (f"environment.tau_ext_{n}", port["tau_ext"]),
        ]
    return pairs


def signals(scenario: Scenario) -> list[SignalSpec]:
    specs = []
    for n in range(1, scenario.robot.segments + 1):
        specs += [
            SignalSpec(
                f"penetration_{n}",
                "m",
                f"segment {n}: deepest contact penetration",
                source=f"environment.penetration_{n}",
            ),
            SignalSpec(
                f"contact_force_{n}",
                "N",
                f"segment {n}: contact force magnitude",
                source=f"environment.contact_force_{n}",
            ),
            SignalSpec(
                f"tau_ext_{n}",
                "N.m",
                f"segment {n}: external torque from contact and table",
                source=f"environment.tau_ext_{n}",
            ),
        ]
    specs += [
        SignalSpec(
            "contact_impulse",
            "N.s",
            "time integral of the contact force magnitudes",
            source="environment.contact_impulse",
        ),
        SignalSpec(
            "E_dissipated_env",
            "J",
            "energy dissipated by contact and friction",
            source="environment.E_dissipated",
        ),
        SignalSpec(
            "passivity_damping",
            "N.m.s/rad",
            "damping the environment's passivity controller adds to every degree of freedom",
            source="environment.passivity_damping",
        ),
        SignalSpec(
            "W_arm_env",
            "J",
            "work of the environment's torques on the arm",
            source="environment.W_arm",
        ),
    ]
    for o in range(1, len(scenario.robot.environment.get("objects", [])) + 1):
        for name, unit in (("x", "m"), ("y", "m"), ("yaw", "rad"), ("upright", "")):
            specs.append(
                SignalSpec(
                    f"object{o}_{name}",
                    unit,
                    f"object {o}: {name}",
                    source=f"environment.object_{name}_{o}",
                )
            )
    return specs


def _per_segment(file: str, key: str, value: Any, n: int) -> list[float]:
    from hil.scenario import fail

    if isinstance(value, list):
        if len(value) != n:
            raise fail(file, key, f"has {len(value)} values for {n} segments")
        return [_number(file, f"{key}[{i}]", v) for i, v in enumerate(value)]
    return [_number(file, key, value)] * n


def _point(file: str, key: str, value: Any) -> tuple[float, float]:
    from hil.scenario import fail

    if not isinstance(value, list) or len(value) != 2:
        raise fail(file, key, f"must be [x, y], got {value!r}")
    return _number(file, f"{key}[0]", value[0]), _number(file, f"{key}[1]", value[1])


def _number(file: str, key: str, value: Any) -> float:
    from hil.scenario import fail

    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise fail(file, key, f"must be a finite number, got {value!r}")
    return float(value)
