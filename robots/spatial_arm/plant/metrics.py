"""The spatial arm's task metrics (summary.json), scored on the true recorded signals.

A goal's window runs from the first sample the controller reports pursuing it (SpatialTaskState
target_index) to the sample before the next goal's (or the run's end). In it:
- `tip_error`: the true tip's distance from the goal [m] where the controller declared the goal
  settled (phase 3), else at the window's end (a goal given up);
- `time_to_settle`: from the window's start until the true tip enters `task.band` of the goal for
  good (None if it never does);
Over the goals (`targets`): mean, standard deviation and largest tip error, the largest time to
settle (`time_to_settle`, infinite if a goal never settled in the band) and the mean, and
`targets_settled` (declared settled with the true tip within `task.tolerance` plus the camera's
3-sigma). `droop`: how far the start's tip hangs below the straight arm's, along gravity [m].
Shape: the distances from the curve's points to the true backbone at the end [m].
Configuration: each step's largest true bend error at the end of its window [rad].
The controller's reports only cut the windows; scores are on the true signals.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from hil.scenario import Scenario
    from robots.spatial_arm.plant.rig import SpatialArm

SETTLED = 3
DONE = 4
# a run succeeds (summary `success`, hil batch's success rate) within these [m], [rad]: a tip mean
# of 5 mm and a largest of 15 mm (README, "The spatial arm": about 6 and 17 times a marker's
# 3-D noise of the realistic camera, 1 % and 3 % of the arm's length), a shape within 5 mm
TIP_MEAN_LIMIT = 5e-3
TIP_MAX_LIMIT = 15e-3
SHAPE_LIMIT = 5e-3
BEND_LIMIT = 0.02
CONFINING_BENDS = (0.12, 0.15, 0.2, 0.3, 0.5, 1.0)  # [m] pipe bend radii of the comparison


def bends(signals: Mapping[str, np.ndarray], segments: int, k: int) -> np.ndarray:
    """The true bends at sample k: (theta_x_1, theta_y_1, ...)."""
    return np.array(
        [signals[f"theta_{axis}_{i}"][k] for i in range(1, segments + 1) for axis in "xy"]
    )


def tip(signals: Mapping[str, np.ndarray], segments: int) -> np.ndarray:
    """The true tip over the run, (samples, 3)."""
    return np.column_stack([signals[f"tip_{c}_{segments}"] for c in "xyz"])


def windows(signals: Mapping[str, np.ndarray]) -> list[tuple[int, int, int]]:
    """(goal index, first sample, last sample) of every goal the controller pursued."""
    index = np.nan_to_num(np.asarray(signals["target_index"], dtype=float), nan=-1.0)
    phase = np.nan_to_num(np.asarray(signals["phase"], dtype=float), nan=0.0)
    active = phase > 0
    out: list[tuple[int, int, int]] = []
    k, n = 0, len(index)
    while k < n:
        if not active[k] or phase[k] == DONE:
            k += 1
            continue
        start, goal = k, int(index[k])
        while k < n and int(index[k]) == goal and phase[k] != DONE:
            k += 1
        out.append((goal, start, k - 1))
    return out


def settle_time(
    t: np.ndarray, distance: np.ndarray, start: int, end: int, band: float
) -> float | None:
    """From t[start] until the distance stays within `band` to t[end]; None if it does not end
    within it."""
    inside = distance[start : end + 1] <= band
    if not inside[-1]:
        return None
    outside = np.flatnonzero(~inside)
    first = start + (int(outside[-1]) + 1 if outside.size else 0)
    return float(t[first] - t[start])


def _stats(values: list[float], name: str, unit_scale: float = 1.0) -> dict[str, Any]:
    if not values:
        return {f"{name}_mean": None, f"{name}_std": None, f"{name}_max": None}
    a = np.asarray(values) * unit_scale
    return {
        f"{name}_mean": float(a.mean()),
        f"{name}_std": float(a.std()),
        f"{name}_max": float(a.max()),
    }


def task_metrics(arm: SpatialArm, scenario: Scenario, signals: Mapping[str, Any]) -> dict[str, Any]:
    from robots.spatial_arm.controller import kinematics

    n = scenario.robot.segments
    model = arm.model(scenario)
    true_tip = tip(signals, n)
    straight = kinematics.tip(model, np.zeros(model.n_q))
    out: dict[str, Any] = {"droop": droop(model, true_tip[0], straight) if len(true_tip) else None}
    kind = scenario.task.kind
    if kind in ("point", "object"):
        out.update(_tip_metrics(arm, scenario, signals, true_tip))
    elif kind == "confined":
        out.update(_confined_metrics(arm, scenario, signals, model, true_tip))
    elif kind == "shape":
        out.update(_shape_metrics(arm, scenario, signals, model))
    elif kind == "configuration":
        out.update(_bend_metrics(arm, scenario, signals))
    return out


def droop(model: Any, tip_now: np.ndarray, straight: np.ndarray) -> float:
    """How far the tip hangs below the straight arm's [m]: its displacement along gravity."""
    g = np.asarray(model.gravity, dtype=float)
    norm = float(np.linalg.norm(g))
    return float((tip_now - straight) @ g / norm) if norm > 0.0 else 0.0


def goal_points(arm: SpatialArm, scenario: Scenario) -> list[np.ndarray]:
    plan = arm.task_layout(scenario)
    if scenario.task.kind == "object" and plan.object is not None:
        return [np.asarray(plan.object) + np.asarray(scenario.robot.offset)]
    return [np.asarray(g) for g in plan.goals]


def _tip_metrics(
    arm: SpatialArm, scenario: Scenario, signals: Mapping[str, Any], true_tip: np.ndarray
) -> dict[str, Any]:
    goals = goal_points(arm, scenario)
    t = np.asarray(signals["time"], dtype=float)
    phase = np.nan_to_num(np.asarray(signals["phase"], dtype=float))
    errors: list[float] = []
    times: list[float] = []
    settled = 0
    judged = scenario.task.tolerance + 3.0 * scenario.camera.noise
    for goal, start, end in windows(signals):
        if goal >= len(goals):
            continue
        distance = np.linalg.norm(true_tip - goals[goal], axis=1)
        declared = np.flatnonzero(phase[start : end + 1] == SETTLED)
        at = start + int(declared[0]) if declared.size else end
        errors.append(float(distance[at]))
        settled += int(declared.size > 0 and distance[at] <= judged)
        found = settle_time(t, distance, start, end, scenario.task.band)
        if found is not None:
            times.append(found)
    return {
        "targets": len(goals),
        "targets_pursued": len(errors),
        "targets_settled": settled,
        **_stats(errors, "tip_error"),
        "time_to_settle": float(np.max(times)) if len(times) == len(goals) else math.inf,
        "time_to_settle_mean": float(np.mean(times)) if times else None,
        "targets_in_band": len(times),
        "success": bool(
            settled == len(goals)
            and errors
            and float(np.mean(errors)) < TIP_MEAN_LIMIT
            and max(errors) < TIP_MAX_LIMIT
        ),
    }


def _confined_metrics(
    arm: SpatialArm,
    scenario: Scenario,
    signals: Mapping[str, Any],
    model: Any,
    true_tip: np.ndarray,
) -> dict[str, Any]:
    """The pipe: how far the true arm went into the wall (its points past the entrance, their
    distance from the axis plus half the width, less the radius; positive: into the wall), the
    tip's distance from the goal at the end, when it first came within the band for good; and
    the minimum confining radius of the soft arm and of a rigid-link arm of the same reach
    around circular pipes of the bend radii CONFINING_BENDS (`confined.confining_table`)."""
    from robots.spatial_arm.controller import confined

    r = scenario.robot
    pipe = confined.Pipe(np.asarray(r.pipe, dtype=float), r.pipe_radius)
    where = confined.arm_stations(model)
    n = r.segments
    rows = range(0, len(signals["time"]), 5)  # every 5th sample: 0.1 s at 50 Hz
    qs = np.array([bends(signals, n, k) for k in rows])
    p = kinematics_points(model, qs, where)
    inside = pipe.depth(p) > 0.0
    wall = pipe.distance(p) + 0.5 * r.width - r.pipe_radius
    penetration = float(np.max(np.where(inside, wall, -np.inf))) if inside.any() else None
    goal = pipe.along(r.goal_depth)
    distance = np.linalg.norm(true_tip - goal, axis=1)
    t = np.asarray(signals["time"], dtype=float)
    reached_at = settle_time(t, distance, 0, len(t) - 1, scenario.task.band)
    judged = scenario.task.tolerance + 3.0 * scenario.camera.noise
    return {
        "penetration_max": penetration,
        "goal_error": float(distance[-1]),
        "goal_reached": bool(distance[-1] <= judged),
        "success": bool(distance[-1] <= judged and (penetration is None or penetration <= 0.0)),
        "time_to_goal": reached_at if reached_at is not None else math.inf,
        "contact_impulse": None,  # the pipe's wall is not a body in this rig: measured, not felt
        "insertion": float(np.max(np.where(inside, pipe.depth(p), 0.0))),
        "confining": confining_rows(arm, scenario),
    }


_CONFINING: dict[str, list[dict[str, float]]] = {}


def confining_rows(arm: SpatialArm, scenario: Scenario) -> list[dict[str, float]]:
    """The comparison's rows (computed once per arm and width: a shape fit per bend radius)."""
    from robots.spatial_arm.controller import confined

    model = arm.model(scenario)
    key = repr((model, scenario.robot.width))
    if key not in _CONFINING:
        _CONFINING[key] = [
            {"bend_radius": R, "soft": soft, "rigid": rigid}
            for R, soft, rigid in confined.confining_table(
                model, np.asarray(CONFINING_BENDS), scenario.robot.width
            )
        ]
    return _CONFINING[key]


def kinematics_points(model: Any, qs: np.ndarray, where: Any) -> np.ndarray:
    from robots.spatial_arm.controller.kinematics import points

    return np.asarray(points(model, qs, where)[0])


def _shape_metrics(
    arm: SpatialArm, scenario: Scenario, signals: Mapping[str, Any], model: Any
) -> dict[str, Any]:
    from robots.spatial_arm.controller import kinematics

    curve = np.asarray(arm.task_layout(scenario).curve, dtype=float)
    n = scenario.robot.segments
    q = bends(signals, n, len(signals["time"]) - 1)
    line = kinematics.backbone(model, q, 32)
    distances = [float(point_to_polyline(p, line)) for p in curve]
    return {
        "curve_points": len(curve),
        **_stats(distances, "shape_error"),
        "tip_error_final": float(np.linalg.norm(line[-1] - curve[-1])),
        "success": bool(max(distances) < SHAPE_LIMIT),
    }


def point_to_polyline(p: np.ndarray, line: np.ndarray) -> float:
    """The distance from p to the polyline's nearest segment [m]."""
    a, b = line[:-1], line[1:]
    ab = b - a
    length2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
    s = np.clip(np.einsum("ij,ij->i", p - a, ab) / length2, 0.0, 1.0)
    nearest = a + s[:, None] * ab
    return float(np.min(np.linalg.norm(nearest - p, axis=1)))


def _bend_metrics(
    arm: SpatialArm, scenario: Scenario, signals: Mapping[str, Any]
) -> dict[str, Any]:
    steps = arm.task_layout(scenario).bends
    n = scenario.robot.segments
    errors: list[float] = []
    for goal, _, end in windows(signals):
        if goal < len(steps):
            target = np.asarray(steps[goal][1:])
            errors.append(float(np.max(np.abs(bends(signals, n, end) - target))))
    return {
        "steps": len(steps),
        "steps_pursued": len(errors),
        **_stats(errors, "bend_error"),
        "success": bool(len(errors) == len(steps) and errors and max(errors) < BEND_LIMIT),
    }
