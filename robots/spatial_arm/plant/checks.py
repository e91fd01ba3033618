"""The spatial arm's scenario checks that are code (its keys and rules are SpatialArmSpec's):
the FMU tables' parameters, the task's goals, curve and bend steps against the arm."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from hil.scenario import Scenario
    from robots.spatial_arm.plant.rig import SpatialArm


def check(arm: SpatialArm, scenario: Scenario) -> None:
    from hil.scenario import fail

    file, r, task = scenario.source, scenario.robot, scenario.task
    arm.given_body(scenario)  # each raises naming the key
    arm.given_cylinder(scenario)
    reach = arm.reach(scenario)
    for name, points in (("robot.goals", r.goals), ("robot.curve", r.curve)):
        for k, point in enumerate(points):
            if sum(c * c for c in point) ** 0.5 > reach:
                raise fail(
                    file,
                    f"{name}[{k}]",
                    f"{list(point)} is beyond the arm's reach of {reach:.3g} m from the base",
                )
    if task.kind == "shape" and r.curve and len(r.curve) < 2:
        raise fail(file, "robot.curve", "a curve needs at least 2 points")
    width = 1 + 2 * r.segments
    last = -1.0
    for k, step in enumerate(r.bends):
        if len(step) != width:
            raise fail(
                file,
                f"robot.bends[{k}]",
                f"needs {width} values [time, theta_x_1, theta_y_1, ...], got {len(step)}",
            )
        if step[0] <= last:
            raise fail(file, f"robot.bends[{k}]", "step times must increase")
        last = step[0]
    if task.kind == "confined":
        _check_pipe(scenario)
    if scenario.timing.step > 1e-3 + 1e-15:
        raise fail(file, "timing.step", "the arm body steps at most 1 ms (ArmBody's step_size)")
    arm.start_bends(scenario)  # raises naming robot.body when the arm cannot rest


def _check_pipe(scenario: Scenario) -> None:
    from hil.scenario import fail

    file, r = scenario.source, scenario.robot
    if len(r.pipe) < 2:
        raise fail(file, "robot.pipe", "the confined task needs the pipe's axis: 2 points or more")
    points = [tuple(p) for p in r.pipe]
    length = sum(
        sum((a - b) ** 2 for a, b in zip(p, q, strict=True)) ** 0.5
        for p, q in zip(points, points[1:], strict=False)
    )
    if any(p == q for p, q in zip(points, points[1:], strict=False)):
        raise fail(file, "robot.pipe", "two consecutive axis points are the same")
    if r.goal_depth > length:
        raise fail(
            file,
            "robot.goal_depth",
            f"{r.goal_depth:g} m is beyond the pipe's axis of {length:.3g} m",
        )
    room = r.pipe_radius - 0.5 * r.width - scenario.task.clearance
    if room <= 0.0:
        raise fail(
            file,
            "robot.pipe_radius",
            f"{r.pipe_radius:g} m leaves no room for the arm's width {r.width:g} m and the "
            f"clearance {scenario.task.clearance:g} m",
        )
