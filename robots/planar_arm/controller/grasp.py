"""Grasp-and-place tasks of the planar arm with its soft gripper (issue 12).

The thesis's planar grasping manipulator approaches a randomly placed object along "concentric
approach circles" that shrink onto it, grasps it, carries it to a place location and releases
it. `draw_grasp_task` draws such a task: an object and a place location that the arm can grasp
at, both plannable (robots.planar_arm.controller.grasp_planner) from the arm's start with room to
spare, from the scenario's `numpy.random.Generator`.

Invariant: the draw is deterministic: it takes all its randomness from the Generator passed in.
"""

from __future__ import annotations

import math

import numpy as np

from robots.planar_arm.controller.grasp_carry import plan_carry
from robots.planar_arm.controller.grasp_clearance import ARM_WIDTH, Floats, Pose, clearance
from robots.planar_arm.controller.grasp_planner import MARGIN, Arm, plan_approach
from robots.planar_arm.controller.gripper import GripperGeometry, grasp_point, tip_for_grasp

DRAW_ATTEMPTS = 200
DRAW_SHARE = 0.7  # share of each curvature range that drawn grasp poses need (see draw_targets)
START_MARGIN = 0.01  # [m] a drawn object's clearance from the arm in its start configuration
SEPARATION = 0.06  # [m] least distance between a drawn object and its place location
# [m] a drawn task is kept only if its plans keep this much more than `margin`: the controller
# plans again from estimates (the object's centre and the arm's start a fraction of a millimetre
# off, the grasp configuration settled a little off its plan), and a draw on the edge of
# plannable would fail there
DRAW_SLACK = 2e-3
# [1/m] and the approach must also be plannable (with `margin`) from the start configuration
# shaken by this much per segment, both ways (alternating signs): the controller plans from its
# estimate of the start, a tenth of a 1/m or so off, and some layouts are plannable from the
# exact start only
START_SHAKE = 0.15


def draw_grasp_task(
    rng: np.random.Generator,
    lengths: Floats,
    base: Pose,
    lower: Floats,
    upper: Floats,
    geometry: GripperGeometry,
    object_radius: float,
    start_kappas: Floats,
    *,
    share: float = DRAW_SHARE,
    start_margin: float = START_MARGIN,
    separation: float = SEPARATION,
    margin: float = MARGIN,
    width: float = ARM_WIDTH,
    plannable: bool = True,
    slack: float = DRAW_SLACK,
    shake: float = START_SHAKE,
    attempts: int = DRAW_ATTEMPTS,
) -> tuple[tuple[float, float], tuple[float, float]]:
    """An object position and a place position [m] for a grasp-and-place task.

    Each is the grasp point of a tip pose drawn as `draw_targets` draws targets (curvatures
    uniform within the middle `share` of each segment's range), and must be a grasp pose that
    the heading-constrained IK reaches from `start_kappas` within those shrunk bounds. The object
    keeps `start_margin` [m] from the arm in its start configuration (backbone and open
    fingers); the place is at least `separation` [m] from the object and does not overlap the
    object's start (two radii plus `margin` apart). With `plannable`, the draw is also kept
    only if `plan_approach` from the start and `plan_carry` (with the retreat) succeed with
    `margin + slack`, and `plan_approach` with `margin` from the start shaken by `shake` [1/m]
    both ways, so the controller, planning with `margin` from its estimates, can do the task.
    Deterministic: all randomness comes from `rng`.

    Raises
    ------
    ValueError
        When no draw within `attempts` meets these conditions.
    """
    arm = Arm.of(lengths, base, lower, upper, geometry, width)
    if not 0.0 < share <= 1.0:
        raise ValueError(f"grasp task: share {share} must be in (0, 1]")
    start = np.asarray(start_kappas, dtype=float)
    mid, half = 0.5 * (arm.lower + arm.upper), 0.5 * (arm.upper - arm.lower) * share
    shrunk = Arm(arm.lengths, arm.base, mid - half, mid + half, geometry, width)

    def draw() -> tuple[np.ndarray, float] | None:
        kappas = rng.uniform(shrunk.lower, shrunk.upper)
        tip = arm.tip(kappas)
        point = grasp_point(geometry, (float(tip[0]), float(tip[1]), float(tip[2])))
        pose = tip_for_grasp(geometry, (float(point[0]), float(point[1])), float(tip[2]))
        if shrunk.solve(pose, start, max_iter=100) is None:
            return None
        return point, float(tip[2])

    for _ in range(attempts):
        drawn = draw()
        if drawn is None:
            continue
        centre = (float(drawn[0][0]), float(drawn[0][1]))
        other = draw()
        if other is None:
            continue
        place = (float(other[0][0]), float(other[0][1]))
        apart = math.dist(centre, place)
        if apart < max(separation, 2.0 * object_radius + margin):
            continue
        near = clearance(
            start,
            centre,
            object_radius,
            arm.lengths,
            arm.base,
            geometry,
            geometry.theta_open,
            width=width,
        )
        if near < start_margin:
            continue
        if plannable:
            try:
                approach = plan_approach(
                    centre,
                    object_radius,
                    start,
                    lengths,
                    base,
                    lower,
                    upper,
                    geometry,
                    margin=margin + slack,
                    width=width,
                )
                plan_carry(
                    place,
                    approach.waypoints[-1][0],
                    approach.waypoints[-1][1][2],
                    lengths,
                    base,
                    lower,
                    upper,
                    geometry,
                    object_radius=object_radius,
                    margin=margin + slack,
                    width=width,
                )
                pattern = np.where(np.arange(start.size) % 2 == 0, shake, -shake)
                for shaken in (start + pattern, start - pattern):
                    plan_approach(
                        centre,
                        object_radius,
                        shaken,
                        lengths,
                        base,
                        lower,
                        upper,
                        geometry,
                        margin=margin,
                        width=width,
                    )
            except ValueError:
                continue
        return centre, place
    raise ValueError(f"grasp task: no object and place found in {attempts} draws")
