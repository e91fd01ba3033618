"""Carrying the held object to its place: the planar arm's grasp point (where the held object's
centre sits) moved along a straight line to the place location, the heading changing linearly if
it must (issue 12). The place heading is the reachable one nearest the grasp
heading from which, given the object's radius, the open gripper can also back off
(robots.planar_arm.controller.grasp_planner.plan_retreat).

Invariant: every returned configuration lies within [lower, upper] and meets its tip pose by the
IK's tolerance; consecutive configurations come from warm-started IK; the plan is a
deterministic function of its inputs.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from robots.planar_arm.controller.grasp_clearance import ARM_WIDTH, Floats, Pose
from robots.planar_arm.controller.grasp_planner import (
    HEADING_STEP,
    MARGIN,
    Arm,
    GraspPlan,
    headings_around,
    plan_retreat,
)
from robots.planar_arm.controller.gripper import GripperGeometry, grasp_point, tip_for_grasp

CARRY_STEP = 0.02  # [m] grasp point travel between carry waypoints


def plan_carry(
    place: Floats,
    current_kappas: Floats,
    heading: float,
    lengths: Floats,
    base: Pose,
    lower: Floats,
    upper: Floats,
    geometry: GripperGeometry,
    *,
    step: float = CARRY_STEP,
    heading_step: float = HEADING_STEP,
    object_radius: float | None = None,
    radii: Floats | None = None,
    margin: float = MARGIN,
    width: float = ARM_WIDTH,
) -> GraspPlan:
    """Waypoints that carry the held object from the grasp configuration to `place`.

    The grasp point moves along the straight line from where it is now (the grasp point of
    `current_kappas`' tip) to `place`, at most `step` [m] per waypoint, the heading changing
    linearly from `heading` [rad] to the place heading, at most `heading_step` [rad] per
    waypoint; each waypoint is solved warm-started from the previous one. The place heading is
    the one nearest `heading` (on a HEADING_STEP grid) for which the whole line is reachable
    and, when `object_radius` is given, the retreat (`plan_retreat` with `radii`, `margin`,
    `width`) after release is possible too.

    Raises
    ------
    ValueError
        When no place heading gives a reachable carry (and retreat).
    """
    arm = Arm.of(lengths, base, lower, upper, geometry, width)
    if not step > 0.0 or not heading_step > 0.0:
        raise ValueError(f"grasp planning: carry steps {step} m, {heading_step} rad must be > 0")
    current = np.clip(np.asarray(current_kappas, dtype=float), arm.lower, arm.upper)
    origin = grasp_point(geometry, tuple(arm.tip(current)))  # type: ignore[arg-type]
    target = np.array(place, dtype=float)
    where = f"place ({place[0]:.4f}, {place[1]:.4f}) m"
    reach = float(np.sum(arm.lengths)) + geometry.grasp_offset
    if math.hypot(target[0] - arm.base[0], target[1] - arm.base[1]) > reach:
        raise ValueError(f"grasp planning: the {where} is beyond the arm's reach {reach:.3f} m")
    # the place's reachable headings: continuation round it from the carry heading if that is
    # reachable there, else from whatever heading a position-only solve finds
    seed = arm.solve(tip_for_grasp(geometry, tuple(target), heading), current)
    start_heading = heading
    if seed is None:
        seed = arm.seed(target, 0.0, current)
        if seed is None:
            raise ValueError(f"grasp planning: no grasp pose reaches the {where}")
        tip_heading = float(arm.tip(seed)[2])
        start_heading = heading + math.remainder(tip_heading - heading, 2.0 * math.pi)
    # nearest first: `headings_around` yields them in that order when it starts at `heading`
    finals: Iterable[float] = (
        h for _, h, _ in headings_around(arm, target, 0.0, start_heading, seed)
    )
    if start_heading != heading:
        finals = sorted(finals, key=lambda h: abs(h - heading))
    distance = float(np.linalg.norm(target - origin))
    for final in finals:
        turn = final - heading
        count = max(1, math.ceil(distance / step), math.ceil(abs(turn) / heading_step))
        waypoints = []
        previous = current
        for i in range(1, count + 1):
            s = i / count
            point = origin + s * (target - origin)
            h = heading + s * turn
            pose = tip_for_grasp(geometry, (float(point[0]), float(point[1])), h)
            solved = arm.solve(pose, previous)
            if solved is None:
                break
            actual = float(arm.tip(solved)[2])
            waypoints.append(
                (solved, (pose[0], pose[1], actual + math.remainder(h - actual, 2 * math.pi)))
            )
            previous = solved
        else:
            if object_radius is not None:
                try:
                    plan_retreat(
                        place,
                        object_radius,
                        previous,
                        final,
                        lengths,
                        base,
                        lower,
                        upper,
                        geometry,
                        radii=radii,
                        margin=margin,
                        width=width,
                    )
                except ValueError:
                    continue
            return GraspPlan(
                start=current,
                waypoints=tuple(waypoints),
                heading=math.remainder(final, 2.0 * math.pi),
                radii=(),
                centre=(float(place[0]), float(place[1])),
                standoffs=(0.0,) * len(waypoints),
                clearance=math.inf,
            )
    raise ValueError(
        f"grasp planning: no place heading carries the object from ({origin[0]:.4f}, "
        f"{origin[1]:.4f}) m to the {where}"
        + ("" if object_radius is None else " and backs off clear of it")
    )
