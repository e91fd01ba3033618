"""The planar arm's scenario checks: its rules between keys as data (`RULES`, hil.schema), and
the checks that are truly code (`check`): the FMUs' parameters, each cylinder's geometry, the
start pose, the gripper's reachable bend, objects and walls clear of the arm at the start, and
every task point within the arm's reach.

Invariant: `check` runs after every declared key and rule of the scenario has held (hil.schema),
so it reads the keys' values as valid; each problem is one line naming the key (hil.scenario).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from controllers import kinematics
from hil.schema import Given, Is, MinItems, Needs, OneOf
from rigbus.protocol import Protocol
from robots.planar_arm.controller.tasks import TASK_KINDS
from robots.planar_arm.plant import body, environment, gripper

IK_RANGE_SHARE = 0.9  # of each segment's reachable curvature range that IK may use: the rest is
# left for the curvature loop to correct in

if TYPE_CHECKING:
    from hil.scenario import Scenario
    from robots.planar_arm.plant.rig import PlanarArm

TASKS = ("curvature_profile", *TASK_KINDS)
SEGMENT_GEOMETRY = (
    "bore",
    "stroke",
    "x_seal",
)  # the segment's circuit takes them from its cylinder
GEOMETRY_WHY = (
    "the gas circuit takes the drive cylinder's geometry: set stroke, bore or x_start in "
    "robot.cylinder"
)


def _kind(name: str) -> tuple[str, Is]:
    return ("task.kind", Is(name))


RULES = (
    Needs("task.kind", OneOf(TASKS)),
    Needs(
        "robot.environment",
        Given(),
        when=("robot.gripper", Given(empty=True)),
        why="the fingers act on the world through its contact",
    ),
    Needs(
        "task.targets",
        Given(False),
        when=_kind("path"),
        why="a path task takes task.paths [x0, y0, x1, y1]",
    ),
    Needs(
        "task.paths",
        Given(False),
        when=_kind("point_to_point"),
        why="a point_to_point task takes task.targets [x, y]",
    ),
    Needs("task.goal", Given(), when=_kind("pipe"), why="the goal [x, y] deep in the channel"),
    Needs(
        "task.centreline",
        MinItems(2, "point"),
        when=_kind("pipe"),
        why="the channel's centreline",
    ),
    Needs("robot.environment.walls", Given(), when=_kind("pipe"), why="the channel's walls"),
    Needs(
        "robot.gripper",
        Given(empty=True),
        when=_kind("grasp"),
        why="its fingers hold the object",
    ),
    Needs(
        "robot.environment.objects",
        Given(),
        when=_kind("grasp"),
        why="the first is the object to grasp",
    ),
)


def check(arm: PlanarArm, s: Scenario) -> None:
    """The arm's checks that are code, in the order its parts depend on each other."""
    protocol = Protocol()
    if environment.present(s):
        environment.objects(s)  # the markers and a grasp task's draw count on them
    if s.camera and arm.markers(s) > protocol.count("CameraMarker"):
        raise _fail(s, "robot.segments", "more markers than the DBC's CameraMarker frames")
    for name in ("segment_decimation", "cylinder_decimation"):
        if s.control_ticks % getattr(s.robot, name):
            raise _fail(
                s, f"robot.{name}", f"must divide the control period's {s.control_ticks} ticks"
            )
    _fmu_parameters(arm, s)
    _cylinders(arm, s, protocol)
    try:
        arm.start_pistons(s)
    except ValueError as exc:
        raise _fail(s, "robot.segment.theta_start", f"no piston holds it: {exc}") from None
    if gripper.present(s):
        _gripper(arm, s, protocol)
    if environment.present(s):
        _placements(arm, s, arm.environment_parameters(s))
    if s.task.kind in TASK_KINDS:
        _task_space(arm, s)
    else:
        _curvature_profile(arm, s, protocol)


def _fail(s: Scenario, key: str, reason: str) -> Exception:
    from hil.scenario import fail

    return fail(s.source, key, reason)


def _fmu_parameters(arm: PlanarArm, s: Scenario) -> None:
    """Every per-actuator parameter is one of its FMU's, within the FMU's range; the segment's
    circuit geometry comes from its cylinder."""
    from hil.scenario import check_parameter, fmu_interface

    r = s.robot
    interfaces = {
        "segment": fmu_interface(s.source, "robot.segment_fmu", r.segment_fmu),
        "cylinder": fmu_interface(s.source, "robot.cylinder_fmu", r.cylinder_fmu),
    }
    for table, interface in interfaces.items():
        for given in arm._given(s, table):
            for name, (value, key) in given.items():
                if table == "segment" and name in SEGMENT_GEOMETRY:
                    raise _fail(s, key, GEOMETRY_WHY)
                check_parameter(s.source, key, interface, name, value)
    if body.present(s):
        segments, cylinders = arm.parameters(s, "segment"), arm.parameters(s, "cylinder")
        body.check(s, arm._given(s, "segment"), segments, cylinders)


def _cylinders(arm: PlanarArm, s: Scenario, protocol: Protocol) -> None:
    """Each piston starts within its stroke, and the stroke is one the bus can carry."""
    piston_max = protocol.signal_range("DriveCommand1", "piston_setpoint")[1]
    n = s.robot.segments
    for i, cylinder in enumerate(arm.parameters(s, "cylinder")):
        stroke = cylinder["stroke"]
        if not 0.0 <= cylinder["x_start"] <= stroke:
            raise _fail(s, _key("x_start", n, i), f"must lie within the stroke [0, {stroke:g}] m")
        if stroke > piston_max:
            raise _fail(
                s,
                _key("stroke", n, i),
                f"{stroke:g} m is beyond the {piston_max:g} m that DriveStatus/DriveCommand "
                "can carry",
            )


def _key(name: str, count: int, index: int) -> str:
    key = f"robot.cylinder.{name}"
    return key if count == 1 else f"{key} (actuator {index + 1})"


def _gripper(arm: PlanarArm, s: Scenario, protocol: Protocol) -> None:
    """The gripper's drive has a frame, its FMUs' parameters are theirs, and its open and
    closed bends are ones the finger pair reaches."""
    from hil.scenario import check_parameter, fmu_interface

    if gripper.node(s) > protocol.count("DriveStatus"):
        raise _fail(s, "robot.segments", "no DriveStatus frame left for the gripper's drive")
    for name, fmu in (("segment", gripper.SEGMENT_FMU), ("cylinder", gripper.CYLINDER_FMU)):
        interface = fmu_interface(s.source, f"robot.gripper.{name}", fmu)
        values = gripper.segment_values(s) if name == "segment" else gripper.table(s, name)
        for key, value in values.items():
            if name == "segment" and key in SEGMENT_GEOMETRY:
                raise _fail(s, f"robot.gripper.segment.{key}", "set it in the cylinder")
            check_parameter(s.source, f"robot.gripper.{name}.{key}", interface, key, value)
    lo, hi = arm.gripper_model(s).reachable_curvature()
    g = gripper.geometry(s)
    for name in ("theta_open", "theta_closed"):
        theta = getattr(g, name)
        if not lo * g.finger_length <= theta <= hi * g.finger_length:
            raise _fail(
                s,
                f"robot.gripper.{name}",
                f"{theta:g} rad is outside the fingers' reachable bend "
                f"[{lo * g.finger_length:.4g}, {hi * g.finger_length:.4g}] rad (their static "
                "equilibrium at either end of the stroke, within theta_max)",
            )


# ---------------------------------------------------------------------- placements

Body = tuple[str, np.ndarray, np.ndarray]  # what it is, its points, each point's reach [m]


def _placements(arm: PlanarArm, s: Scenario, values: Mapping[str, float]) -> None:
    """Every object's start (Environment parameters `values`) clear of the arm's start pose
    (its backbone capsules from the base, and the fingers both at their start bend and open)
    and of the other objects; a grasp task's place clear of the base and of the other
    objects. An object started inside the arm holds the penalty energy of that overlap and
    is pushed out by it, where none was meant: ScenarioError naming the key, as a drawn
    layout is kept clear by construction (robots.planar_arm.controller.grasp.draw_grasp_task)."""
    count = int(values["n_objects"])
    centres = [
        np.array([values[f"object_x0_{o}"], values[f"object_y0_{o}"]]) for o in range(1, count + 1)
    ]
    radii = [values[f"object_radius_{o}"] for o in range(1, count + 1)]
    bodies, base = _bodies(arm, s, values)
    _walls_clear(s, values, bodies)
    names = [_object_key(s, o) for o in range(count)]
    for o, (centre, radius) in enumerate(zip(centres, radii, strict=True)):
        where = f"({centre[0]:.4g}, {centre[1]:.4g}) m"
        for what, points, reach in bodies:
            overlap = radius + reach - _segment_distances(points, centre)
            if np.max(overlap) > 0.0:
                raise _fail(
                    s,
                    names[o],
                    f"an object of radius {radius:g} m at {where} overlaps {what} by "
                    f"{1e3 * float(np.max(overlap)):.1f} mm: it would start inside the arm "
                    "and be pushed out by the contact; place it clear of the arm",
                )
        for other in range(o):
            gap = float(np.linalg.norm(centre - centres[other])) - radius - radii[other]
            if gap < 0.0:
                raise _fail(
                    s,
                    names[o],
                    f"an object at {where} overlaps {names[other]} by {-1e3 * gap:.1f} mm",
                )
    if s.task.kind == "grasp" and s.task.place is not None:
        _place_clear(s, base, centres, radii, names)


def _object_key(s: Scenario, o: int) -> str:
    """The key that placed object `o` (0-based): a grasp task's object is its pick."""
    if s.task.kind == "grasp" and o == 0:
        return "task.pick" if s.task.pick is not None else "task (the drawn object)"
    return f"robot.environment.objects[{o}]"


def _bodies(
    arm: PlanarArm, s: Scenario, values: Mapping[str, float]
) -> tuple[list[Body], tuple[np.ndarray, float]]:
    """The arm's start pose (backbone, and fingers at their start bend and open) as bodies, and
    its base: (centre, half the first segment's width)."""
    segments = arm.parameters(s, "segment")
    kappas = np.array([p.get("theta_start", 0.0) / p["length"] for p in segments])
    lengths = [p["length"] for p in segments]
    widths = [values[f"width_{i}"] for i in range(1, len(lengths) + 1)]
    # the backbone finely sampled: its chords lie within (L / 64)^2 |kappa| / 8 of the arcs
    samples = 64
    poses = kinematics.backbone(kappas, lengths, s.robot.base, per_segment=samples)
    sag = np.repeat(
        [(L / samples) ** 2 * abs(k) / 8.0 for L, k in zip(lengths, kappas, strict=True)],
        samples,
    )
    bodies: list[Body] = [
        ("the arm's start pose", poses[:, :2], np.repeat(np.array(widths) / 2, samples) + sag)
    ]
    if gripper.present(s):
        from robots.planar_arm.controller.gripper import finger_points

        geometry = gripper.geometry(s)
        start = gripper.segment_values(s).get("theta_start", 0.0)
        for theta, state in ((start, "at their start"), (geometry.theta_open, "open")):
            for finger in finger_points(geometry, tuple(poses[-1]), theta, samples):
                bodies.append(
                    (f"the fingers {state}", finger, np.full(samples, geometry.finger_width / 2))
                )
    return bodies, (poses[0, :2], widths[0] / 2)


def _walls_clear(s: Scenario, values: Mapping[str, float], bodies: list[Body]) -> None:
    """The arm starts clear of every wall."""
    for w in range(1, int(values["n_walls"]) + 1):
        wall = np.array(
            [
                [values[f"wall{w}_x_{v}"], values[f"wall{w}_y_{v}"]]
                for v in range(1, int(values[f"wall{w}_n"]) + 1)
            ]
        )
        for what, points, reach in bodies:
            at = np.append(reach, reach[-1])  # each point's: its piece's (the last, its own)
            overlap = at - np.array([np.min(_segment_distances(wall, p)) for p in points])
            worst = int(np.argmax(overlap))
            if overlap[worst] > 0.0:
                raise _fail(
                    s,
                    f"robot.environment.walls[{w - 1}]",
                    f"{what} overlaps the wall by {1e3 * overlap[worst]:.1f} mm at "
                    f"({points[worst][0]:.4g}, {points[worst][1]:.4g}) m: start the arm clear "
                    "of it (robot.base, robot.segment.theta_start, robot.environment.width)",
                )


def _place_clear(
    s: Scenario,
    base: tuple[np.ndarray, float],
    centres: list[np.ndarray],
    radii: list[float],
    names: list[str],
) -> None:
    """A grasp task's place clear of the arm's base and of the other objects."""
    assert s.task.place is not None
    place = np.array(s.task.place)
    where = f"({place[0]:.4g}, {place[1]:.4g}) m"
    base_gap = float(np.linalg.norm(place - base[0])) - radii[0] - base[1]
    if base_gap < 0.0:
        raise _fail(s, "task.place", f"{where} overlaps the arm's base by {-1e3 * base_gap:.1f} mm")
    for other in range(1, len(centres)):
        gap = float(np.linalg.norm(place - centres[other])) - radii[0] - radii[other]
        if gap < 0.0:
            raise _fail(s, "task.place", f"{where} overlaps {names[other]} by {-1e3 * gap:.1f} mm")


def _segment_distances(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Distance [m] from `centre` to each piece of the polyline `points` (shape (k, 2))."""
    a, b = points[:-1], points[1:]
    ab = b - a
    t = np.clip(
        np.sum((centre - a) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-300), 0.0, 1.0
    )
    return np.asarray(np.linalg.norm(centre - (a + t[:, None] * ab), axis=1))


# ---------------------------------------------------------------------- the task


def _curvature_profile(arm: PlanarArm, s: Scenario, protocol: Protocol) -> None:
    """A factor per segment at most, and every curvature the profile asks for reachable."""
    task = s.task
    if len(task.scale) > s.robot.segments:
        raise _fail(
            s, "task.scale", f"has {len(task.scale)} values for {s.robot.segments} segment(s)"
        )
    carried = protocol.signal_range("ControllerState1", "kappa_ref")[1]
    peaks = [(f"task.steps[{j}]", abs(k)) for j, (_, k) in enumerate(task.steps)]
    if task.sine is not None:
        peaks.append(("task.sine", abs(task.sine.offset) + abs(task.sine.amplitude)))
    for i, segment in enumerate(arm.parameters(s, "segment")):
        limit = min(segment["theta_max"] / segment["length"], carried)
        scale = abs(task.scale[i % len(task.scale)])
        for key, peak in peaks:
            if peak * scale > limit:
                raise _fail(
                    s,
                    key,
                    f"curvature {peak * scale:g} 1/m for segment {i + 1} is beyond the "
                    f"reachable {limit:.3g} 1/m (theta_max / length)",
                )


def _task_space(arm: PlanarArm, s: Scenario) -> None:
    """A pipe's channel is one the plan can follow; every target, path and goal within the
    arm's reach; the plan itself can be made."""
    if s.task.kind == "pipe":
        _channel(s)
    points = _task_points(s)
    if points:
        _reachable(arm, s, points, IK_RANGE_SHARE)
    try:
        arm.task_plan(s)
    except ValueError as exc:
        raise _fail(s, "task", str(exc)) from None


def _channel(s: Scenario) -> None:
    from robots.planar_arm.controller.confined import Channel

    walls = s.robot.environment["walls"]
    try:
        Channel(tuple(tuple(map(tuple, w)) for w in walls), s.task.centreline)
    except ValueError as exc:
        raise _fail(s, "robot.environment.walls", str(exc)) from None


def _task_points(s: Scenario) -> list[tuple[str, np.ndarray]]:
    """The task's points the arm must reach, each with its key: targets, the pipe's goal, a
    grasp's pick and place (the grasp poses themselves are checked by grasp_layout), and 11
    points along each path."""
    task = s.task
    points = [(f"task.targets[{i}]", np.array(p)) for i, p in enumerate(task.targets)]
    if task.kind == "pipe" and task.goal is not None:
        points.append(("task.goal", np.array(task.goal)))
    if task.kind == "grasp":
        points += [
            (f"task.{name}", np.array(p))
            for name, p in (("pick", task.pick), ("place", task.place))
            if p is not None
        ]
    for i, path in enumerate(task.paths):
        a, b = np.array(path[:2]), np.array(path[2:])
        if np.linalg.norm(b - a) == 0.0:
            raise _fail(s, f"task.paths[{i}]", "start and end are the same point")
        points += [(f"task.paths[{i}]", a + f * (b - a)) for f in np.linspace(0, 1, 11)]
    return points


def _reachable(
    arm: PlanarArm, s: Scenario, points: list[tuple[str, np.ndarray]], share: float
) -> None:
    """Each point within the arm's reach, using `share` of each segment's curvature range."""
    from robots.planar_arm.controller.ik import solve_ik

    lower, upper, _ = arm.curvature_limits(s)
    mid, half = 0.5 * (lower + upper), 0.5 * (upper - lower) * share
    lengths = [p["length"] for p in arm.parameters(s, "segment")]
    guess = np.zeros(len(lengths))
    for key, point in points:
        result = solve_ik(point, guess, lengths, s.robot.base, mid - half, mid + half)
        if not result.converged:
            raise _fail(
                s,
                key,
                f"({point[0]:.4g}, {point[1]:.4g}) m is out of the arm's reach within "
                f"{100 * share:g} % of each segment's curvature range (closest: "
                f"{1e3 * result.position_error:.3g} mm away)",
            )
        guess = result.kappas
