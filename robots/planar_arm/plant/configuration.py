"""What the planar arm's parameters make of it: each segment's static model and reachable
curvatures, where the pistons start, what the camera sees, the Environment FMU's parameters, a
grasp task's layout, the task plan, and the controller's configuration (ControllerConfig).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from controllers.curvature import PiGains, SegmentModel
from controllers.estimation import BendModel, CameraNoise
from controllers.loop_design import (
    arm_loop_gains,
    effective_delay,
    estimator_delay,
    outer_loop_gains,
)
from hil.seam import camera_timing
from robots.planar_arm.controller.config import ControllerConfig, GripperConfig
from robots.planar_arm.controller.tasks import TASK_KINDS, TaskPlan, draw_paths, draw_targets
from robots.planar_arm.plant import body, environment, gripper
from robots.planar_arm.plant.checks import IK_RANGE_SHARE
from robots.planar_arm.plant.parameters import (
    ACTUATOR_WIDTH,
    NAME,
    _defaults,
    _segment_model,
    parameters,
)

if TYPE_CHECKING:
    from hil.scenario import Scenario

TASK_STREAM = 0x7A5C  # the task's random stream, apart from the camera's (seeded by the seed alone)
DRIVE_SPEED_SHARE = 0.5  # of the drive's no-load speed that curvature moves may ask for
# the [task] keys the controller's plan takes as they are
PLAN_KEYS = (
    "tolerance",
    "settle_time",
    "max_time",
    "speed",
    "acceleration",
    "task_gain",
    "centreline",
    "clearance",
    "grasp_time",
)

_LAYOUTS: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {}  # grasp_layout's


def environment_parameters(s: Scenario) -> dict[str, float]:
    """The Environment FMU's parameters: `[robot.environment]`, the arm's segments, the
    gripper's fingers, and the objects the task places."""
    values = environment.parameters(
        s, parameters(s, "segment"), ACTUATOR_WIDTH[s.robot.actuator], _placed(s)
    )
    if gripper.present(s):
        values.update(gripper.environment_parameters(s))
        # the implicit coupling predicts the fingers with their mobility too
        d_bend = gripper.segment_values(s)["d_bend"]
        values["arm_mobility"] = max(values["arm_mobility"], 1.0 / max(d_bend, 1e-12))
    return values


def _placed(s: Scenario) -> dict[int, tuple[float, float]]:
    """Objects the task places: a grasp task's object, from the seed unless given."""
    if s.task.kind != "grasp":
        return {}
    return {1: grasp_layout(s)[0]}


def start_pistons(scenario: Scenario) -> list[float]:
    """Where each piston starts [m]: at the cylinder's x_start, where the circuit was sealed
    with the segment straight, unless the segment starts bent (theta_start): then at the
    piston position whose static equilibrium is that bend, so that the arm starts at rest
    in its bent configuration instead of springing back."""
    pistons = []
    for model, segment, cylinder in zip(
        segment_models(scenario),
        parameters(scenario, "segment"),
        parameters(scenario, "cylinder"),
        strict=True,
    ):
        theta = segment.get("theta_start", 0.0)
        if theta == 0.0:
            pistons.append(cylinder["x_start"])
        else:
            pistons.append(model.piston_for_curvature(theta / segment["length"]))
    return pistons


def camera_inputs(scenario: Scenario) -> list[str]:
    """What the camera sees: each segment's curvature (the arm's markers), then each
    object's position (its marker, ids segments + 1 ...)."""
    names = [f"kappa_{n}" for n in range(1, scenario.robot.segments + 1)]
    if environment.present(scenario):
        for o in range(1, len(scenario.robot.environment.get("objects", [])) + 1):
            names += [f"object_x_{o}", f"object_y_{o}"]
    return names


def gripper_cylinder(scenario: Scenario) -> dict[str, float]:
    """Every parameter of the gripper's drive cylinder."""
    defaults = _defaults(scenario, "robot.gripper.cylinder", gripper.CYLINDER_FMU)
    return {**defaults, **gripper.table(scenario, "cylinder")}


def gripper_model(scenario: Scenario) -> SegmentModel:
    """The finger pair's static model (as the arm's segment_models)."""
    segment = {
        **_defaults(scenario, "robot.gripper.segment", gripper.SEGMENT_FMU),
        **gripper.segment_values(scenario),
    }
    return _segment_model(segment, gripper_cylinder(scenario))


def grasp_layout(scenario: Scenario) -> tuple[tuple[float, float], tuple[float, float]]:
    """Where a grasp task's object starts and where it is to be placed [m]: the task's
    `pick` and `place`, else drawn from the seed within the reachable workspace."""
    from hil.scenario import fail
    from robots.planar_arm.controller.grasp import draw_grasp_task

    task = scenario.task
    if task.pick is not None and task.place is not None:
        return task.pick, task.place
    key = repr((scenario.seed, task, scenario.robot))  # the draw plans: ~1 s, asked often
    if key in _LAYOUTS:
        return _LAYOUTS[key]
    lower, upper, _ = curvature_limits(scenario)
    mid, half = 0.5 * (lower + upper), 0.5 * (upper - lower) * IK_RANGE_SHARE
    lengths = [p["length"] for p in parameters(scenario, "segment")]
    rng = np.random.default_rng([scenario.seed, TASK_STREAM])
    start = [p.get("theta_start", 0.0) / p["length"] for p in parameters(scenario, "segment")]
    radius = grasp_object(scenario)["radius"]
    try:
        pick, place = draw_grasp_task(
            rng,
            lengths,
            scenario.robot.base,
            mid - half,
            mid + half,
            gripper.geometry(scenario),
            radius,
            start,
        )
    except ValueError as exc:
        raise fail(
            scenario.source,
            "task",
            f"{exc} for an object of radius {radius:g} m "
            "(robot.environment.objects[0].radius): give task.pick and task.place, "
            "or a smaller object",
        ) from None
    layout = (task.pick or pick, task.place or place)
    if len(_LAYOUTS) >= 64:
        _LAYOUTS.clear()
    _LAYOUTS[key] = layout
    return layout


def grasp_object(scenario: Scenario) -> dict[str, float]:
    """The grasp task's object (the first of `[robot.environment] objects`): its keys."""
    from hil.scenario import fail

    items = environment.objects(scenario) if environment.present(scenario) else []
    if not items:
        raise fail(scenario.source, "robot.environment.objects", "a grasp task needs its object")
    return {k: v for k, v in items[0].items() if v is not None}


def reach(scenario: Scenario) -> float:
    """Farthest a marker can be from the base [m]: the arm's length."""
    return sum(p["length"] for p in parameters(scenario, "segment"))


def segment_models(scenario: Scenario) -> list[SegmentModel]:
    return [
        _segment_model(segment, cylinder)
        for segment, cylinder in zip(
            parameters(scenario, "segment"), parameters(scenario, "cylinder"), strict=True
        )
    ]


def controller_config(scenario: Scenario) -> ControllerConfig:
    """What the controller is told: geometry, period, task, gains (designed unless given)."""
    c = scenario.controller
    models = segment_models(scenario)
    segments = parameters(scenario, "segment")
    on_body = body.present(scenario)
    gains = []
    delay = effective_delay(
        estimator_delay(c.estimator, scenario.timing.control_period, c.latency_compensation),
        scenario.timing.control_period,
    )
    for model in models:
        # the design of `hil tune`: a pole-cancelling PI at the scenario's crossover, or
        # lower where the estimator's effective delay leaves less than 60 deg of phase
        designed = outer_loop_gains(model, delay, max_crossover_hz=c.crossover)
        gains.append(
            PiGains(
                Kp=c.kp if c.kp is not None else designed.Kp,
                Ki=c.ki if c.ki is not None else designed.Ki,
            )
        )
    return ControllerConfig(
        robot=NAME,
        lengths=tuple(m.length for m in models),
        base=scenario.robot.base,
        control_period=scenario.timing.control_period,
        cycles=scenario.cycles,
        x_mid=tuple(m.x_seal for m in models),
        x_min=tuple(0.0 for _ in models),
        x_max=tuple(m.stroke for m in models),
        gains=tuple(gains),
        feedforward=tuple(1.0 / m.static_gain() if c.feedforward else 0.0 for m in models),
        profile=scenario.task.profile(),
        plan=task_plan(scenario),
        policy=c.policy,
        timeout=c.timeout,
        bends=tuple(
            BendModel(
                length=p["length"],
                # on the body the inertia the bend carries in the straight arm, with its own mass
                inertia=inertia,
                mass=p["mass"] if on_body else 0.0,
                k_bend=p["k_bend"],
                d_bend=p["d_bend"],
                G_a=p["G_a"],
                theta_max=p["theta_max"],
                vacuum_factor=p.get("vacuum_factor", 1.0),
                p_collapse=p.get("p_collapse", 1e4),
            )
            for p, inertia in zip(segments, _inertias(scenario, segments), strict=True)
        ),
        camera=CameraNoise(
            noise=scenario.camera.noise,
            dropout=scenario.camera.dropout,
            outlier_rate=scenario.camera.outlier_rate,
            outlier_distance=scenario.camera.outlier_distance,
            rate=scenario.camera.rate,
            latency=scenario.camera.latency,
        ),
        estimator=c.estimator,
        latency_compensation=c.latency_compensation,
        torque_std=c.torque_std,
        camera_timing=camera_timing(scenario, markers(scenario)),
        objects=markers(scenario) - scenario.robot.segments - 1,
        gripper=gripper_config(scenario),
        masses=tuple(p["mass"] for p in segments) if on_body else None,
        arm_gains=(
            arm_loop_gains(
                models, [p["mass"] for p in segments], delay, max_crossover_hz=c.crossover
            )
            if on_body and c.kp is None and c.ki is None
            else None
        ),
    )


def _inertias(scenario: Scenario, segments: list[dict[str, float]]) -> list[float]:
    """The inertia each bend carries: on the body (robot.model = "body") the straight arm's
    (the diagonal of its mass matrix), else the lone segment's m L^2 / 20."""
    if body.present(scenario):
        return body.bend_inertias([p["length"] for p in segments], [p["mass"] for p in segments])
    return [p["mass"] * p["length"] ** 2 / 20.0 for p in segments]


def markers(scenario: Scenario) -> int:
    """Markers the camera reports: the base, each segment end, each object."""
    return (
        scenario.robot.segments + 1 + len(camera_inputs(scenario)[scenario.robot.segments :]) // 2
    )


def gripper_config(scenario: Scenario) -> GripperConfig | None:
    """What the controller knows of the gripper: its drive, the pistons that open and close
    it (from the finger pair's static model) and its geometry."""
    if not gripper.present(scenario):
        return None
    geometry = gripper.geometry(scenario)
    model = gripper_model(scenario)
    length = geometry.finger_length
    return GripperConfig(
        node=gripper.node(scenario),
        x_start=gripper_cylinder(scenario)["x_start"],
        x_open=model.piston_for_curvature(geometry.theta_open / length),
        x_closed=model.piston_for_curvature(geometry.theta_closed / length),
        geometry=geometry,
    )


def curvature_limits(scenario: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each segment's reachable curvature range at full stroke (from its static equilibrium
    with the sealed gas circuits: SegmentModel.reachable_curvature) and the curvature rate the
    drive can follow: its no-load speed u_max / Ke * lead / (2 pi), derated by DRIVE_SPEED_SHARE
    for the load, times the segment's curvature per piston travel (1/m per m)."""
    lower, upper, rates = [], [], []
    for model, cylinder in zip(
        segment_models(scenario), parameters(scenario, "cylinder"), strict=True
    ):
        lo, hi = model.reachable_curvature()
        lower.append(lo)
        upper.append(hi)
        speed = cylinder["u_max"] / cylinder["Ke"] * cylinder["lead"] / (2.0 * math.pi)
        rates.append(DRIVE_SPEED_SHARE * speed * abs(model.static_gain()))
    return np.array(lower), np.array(upper), np.array(rates)


def task_plan(scenario: Scenario) -> TaskPlan | None:
    """The task-space plan the controller pursues and the plant scores (None for a curvature
    profile): explicit targets or paths, or drawn from the scenario's seed."""
    task = scenario.task
    if task.kind not in TASK_KINDS:
        return None
    lower, upper, rates = curvature_limits(scenario)
    lengths = [p["length"] for p in parameters(scenario, "segment")]
    base = scenario.robot.base
    rng = np.random.default_rng([scenario.seed, TASK_STREAM])
    targets: tuple[tuple[float, float], ...]
    ends: tuple[tuple[float, float], ...] = ()
    walls: tuple[tuple[tuple[float, float], ...], ...] = ()
    width = 0.0
    object_radius = 0.0
    if task.kind == "grasp":  # the controller is told where to place it, not where it is
        targets = (grasp_layout(scenario)[1],)
        object_radius = float(grasp_object(scenario)["radius"])
    elif task.kind == "pipe":
        assert task.goal is not None  # checked
        targets = (task.goal,)
        walls = tuple(
            tuple((float(x), float(y)) for x, y in wall)
            for wall in scenario.robot.environment.get("walls", [])
        )
        width = max(
            environment.parameters(
                scenario,
                parameters(scenario, "segment"),
                ACTUATOR_WIDTH[scenario.robot.actuator],
            )[f"width_{n}"]
            for n in range(1, scenario.robot.segments + 1)
        )
    elif task.kind == "point_to_point":
        targets = task.targets or tuple(
            draw_targets(rng, lengths, base, lower, upper, task.count, task.margin)
        )
    elif task.paths:
        targets = tuple((p[0], p[1]) for p in task.paths)
        ends = tuple((p[2], p[3]) for p in task.paths)
    else:
        paths = draw_paths(
            rng, lengths, base, lower, upper, task.count, task.path_length, task.margin
        )
        targets = tuple(a for a, _ in paths)
        ends = tuple(b for _, b in paths)
    mid, half = 0.5 * (lower + upper), 0.5 * (upper - lower) * IK_RANGE_SHARE
    return TaskPlan(
        kind=task.kind,
        targets=tuple(targets),
        ends=ends,
        kappa_min=tuple(float(v) for v in mid - half),
        kappa_max=tuple(float(v) for v in mid + half),
        kappa_rate=tuple(float(v) for v in rates),
        walls=walls,
        width=width,
        object_radius=object_radius,
        **{name: getattr(task, name) for name in PLAN_KEYS},
    )
