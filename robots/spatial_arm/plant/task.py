"""The spatial arm's task as the plant sets it: the start (the passive equilibrium under
gravity), the goals, object, curve or bend steps (given, else drawn from the seed among the arm's
static equilibria, so that every draw is statically reachable), and the controller's
configuration.

Draws: piston settings uniform within the middle `DRAW_SHARE` of every stroke, each solved for
its gravity-loaded static equilibrium; a goal is that equilibrium's tip, a curve its backbone, an
object its tip less the task's offset. Drawing among equilibria rather than among points of a box
keeps every goal inside the statically reachable envelope by construction, and the share of the
stroke left at both ends is what the controller has to correct with.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hil.seam import camera_timing

if TYPE_CHECKING:
    from hil.scenario import Scenario
    from robots.spatial_arm.controller.config import SpatialConfig
    from robots.spatial_arm.plant.rig import SpatialArm

TASK_STREAM = 0x5A7A  # the task's random stream, apart from the camera's
DRAW_SHARE = 0.8  # of each stroke the drawn piston settings span (centred)
CURVE_POINTS = 8  # per segment, along a drawn shape's backbone
STEP_TIME = 3.0  # [s] between drawn configuration steps
_LAYOUTS: dict[str, Layout] = {}


@dataclass(frozen=True)
class Layout:
    """What the task asks for, in the base frame."""

    goals: tuple[tuple[float, float, float], ...] = ()
    object: tuple[float, float, float] | None = None
    curve: tuple[tuple[float, float, float], ...] = ()
    bends: tuple[tuple[float, ...], ...] = ()


def start_bends(arm: SpatialArm, scenario: Scenario) -> np.ndarray:
    """The passive equilibrium with every piston at its sealing position."""
    from hil.scenario import fail
    from robots.spatial_arm.controller import equilibrium

    model = arm.model(scenario)
    pistons = np.full(model.n_q, model.x_seal)
    found = equilibrium.static_equilibrium(model, pistons)
    if not bool(found.ok):
        raise fail(
            scenario.source,
            "robot.body",
            "the arm has no stable rest under gravity with its pistons at x_seal "
            f"(residual {float(found.residual):.3g} N m): stiffen it or lighten it",
        )
    return np.asarray(found.q, dtype=float)


def draw_equilibria(arm: SpatialArm, scenario: Scenario, count: int, salt: int) -> np.ndarray:
    """`count` stable equilibria (count, n_q) at seeded piston settings."""
    from robots.spatial_arm.controller import equilibrium

    model = arm.model(scenario)
    rng = np.random.default_rng([scenario.seed, TASK_STREAM, salt])
    start = start_bends(arm, scenario)
    found: list[np.ndarray] = []
    lo = 0.5 * (1.0 - DRAW_SHARE) * model.stroke
    while len(found) < count:
        pistons = lo + rng.random((count, model.n_q)) * DRAW_SHARE * model.stroke
        result = equilibrium.static_equilibrium(model, pistons, start)
        found += [q for q, ok in zip(result.q, result.ok, strict=True) if ok]
    return np.asarray(found[:count])


def layout(arm: SpatialArm, scenario: Scenario) -> Layout:
    key = repr((scenario.seed, scenario.task, scenario.robot))
    if key not in _LAYOUTS:
        if len(_LAYOUTS) >= 32:
            _LAYOUTS.clear()
        _LAYOUTS[key] = _layout(arm, scenario)
    return _LAYOUTS[key]


def _layout(arm: SpatialArm, scenario: Scenario) -> Layout:
    from robots.spatial_arm.controller import kinematics

    r, kind = scenario.robot, scenario.task.kind
    model = arm.model(scenario)
    if kind == "point":
        if r.goals:
            return Layout(goals=tuple(r.goals))
        qs = draw_equilibria(arm, scenario, scenario.task.count, 1)
        return Layout(goals=tuple(map(_point, kinematics.tip(model, qs))))
    if kind == "object":
        if r.object is not None:
            return Layout(object=tuple(r.object))
        q = draw_equilibria(arm, scenario, 1, 2)[0]
        tip = kinematics.tip(model, q) - np.asarray(r.offset)
        return Layout(object=_point(tip))
    if kind == "shape":
        if r.curve:
            return Layout(curve=tuple(r.curve))
        q = draw_equilibria(arm, scenario, 1, 3)[0]
        line = kinematics.backbone(model, q, CURVE_POINTS)
        return Layout(curve=tuple(map(_point, line)))
    if kind == "configuration":
        if r.bends:
            return Layout(bends=tuple(r.bends))
        qs = draw_equilibria(arm, scenario, scenario.task.count, 4)
        return Layout(bends=tuple((0.5 + STEP_TIME * j, *map(float, q)) for j, q in enumerate(qs)))
    return Layout()


def _point(p: Any) -> tuple[float, float, float]:
    return (float(p[0]), float(p[1]), float(p[2]))


def controller_config(arm: SpatialArm, scenario: Scenario) -> SpatialConfig:
    from robots.spatial_arm.controller.config import SpatialConfig

    r, task = scenario.robot, scenario.task
    body = arm.body_parameters(scenario)
    plan = layout(arm, scenario)
    return SpatialConfig(
        robot=arm.name,
        control_period=scenario.timing.control_period,
        cycles=scenario.cycles,
        camera_timing=camera_timing(scenario, arm.markers(scenario), dims=3),
        segments=r.segments,
        body=tuple(sorted(body.items())),
        start=tuple(map(float, start_bends(arm, scenario))),
        task=task.kind,
        estimator=r.estimator,
        goals=plan.goals,
        offset=tuple(r.offset),
        curve=plan.curve,
        bends=plan.bends,
        pipe=tuple(r.pipe),
        pipe_radius=r.pipe_radius,
        goal_depth=r.goal_depth,
        width=r.width,
        clearance=task.clearance,
        insertion_step=r.insertion_step,
        tolerance=task.tolerance,
        settle_time=task.settle_time,
        max_time=task.max_time,
        speed=r.speed,
        acceleration=r.acceleration,
        x_min=0.0,
        x_max=body["stroke"],
        camera_noise=max(scenario.camera.noise, 1e-5),
        dropout=scenario.camera.dropout,
        policy=scenario.controller.policy,
        timeout=scenario.controller.timeout,
    )
