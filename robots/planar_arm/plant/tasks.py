"""Scoring and drawing the planar arm's task-space tasks (issue 11), from the recorded signals.

The plant scores with the truth: the tip position is the forward kinematics of the true
curvatures (the FeaSegment outputs), never the controller's estimate. Which target or path the
controller pursued, and in which phase, comes from its TaskState frames (recorded columns
`target_index`, `phase`); the targets themselves are the plant's own (drawn from the seed by the
same function the controller was configured from), so a controller that reported a wrong target
would be scored against the right one.

Point-to-point, per target: its error is the mean distance of the true tip from the target over
the last `settle_time` of the time the controller spent on it (the window in which it judged the
tip settled), its time to settle the time from the target's start until the true tip enters and
stays within `band` of it. A target counts as settled when the controller reported it settled
before `max_time`. Path, per path: the distance of the true tip from the straight line segment
over the traverse (phase `tracking`), as RMS and maximum.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from controllers import kinematics
from robots.planar_arm.controller.grasp_control import LEGS
from robots.planar_arm.controller.tasks import PHASE, point_to_segment

if TYPE_CHECKING:
    from hil.scenario import Scenario
    from robots.planar_arm.controller.tasks import TaskPlan
    from robots.planar_arm.plant.rig import PlanarArm

ON_TARGET_PHASES = (PHASE["moving"], PHASE["settling"], PHASE["settled"])
SHAPES = 14  # arm shapes drawn over a run


def true_tips(robot: PlanarArm, scenario: Scenario, signals: Mapping[str, Any]) -> np.ndarray:
    """The true tip position at every recorded SYNC, shape (rows, 2) [m]."""
    lengths = [p["length"] for p in robot.parameters(scenario, "segment")]
    kappas = np.column_stack([signals[f"kappa_{n}"] for n in range(1, scenario.robot.segments + 1)])
    return np.array([kinematics.forward(k, lengths, scenario.robot.base)[-1, :2] for k in kappas])


def task_space_metrics(
    robot: PlanarArm, scenario: Scenario, signals: Mapping[str, Any]
) -> dict[str, Any]:
    plan = robot.task_plan(scenario)
    assert plan is not None
    t = np.asarray(signals["time"])
    tips = true_tips(robot, scenario, signals)
    index = np.asarray(signals["target_index"])
    phase = np.asarray(signals["phase"])
    task = scenario.task
    if plan.kind == "point_to_point":
        return _point_to_point(plan.targets, t, tips, index, phase, task)
    if plan.kind == "pipe":
        return _pipe(plan.targets[0], scenario.robot.segments, t, tips, signals, task)
    if plan.kind == "grasp":
        # settling phases that ended at max_time instead of on their condition (the arm, or
        # the carried object, on target and at rest): summary.json counts and lists them
        timeouts = settle_timeouts(t, index, phase, task.max_time, scenario.timing.control_period)
        warned = [
            f"{len(timeouts)} settling phase(s) ended at max_time ({task.max_time:g} s), not on "
            f"target and at rest; first: the {first['leg']} leg's, "
            f"{first['start']:.2f}-{first['end']:.2f} s"
            for first in timeouts[:1]
        ]
        return {
            **_grasp(robot, scenario, t, signals, phase),
            "settle_timeouts": len(timeouts),
            "settle_timeout_phases": timeouts,
            "task_warnings": warned,  # summary.json's warnings
        }
    return _paths(plan.targets, plan.ends, t, tips, index, phase, task)


PLACE_TOLERANCE = 0.01  # [m] the success: the object within 1 cm of its place


def _grasp(
    robot: PlanarArm,
    scenario: Scenario,
    t: np.ndarray,
    signals: Mapping[str, Any],
    phase: np.ndarray,
) -> dict[str, Any]:
    """Grasp-and-place, scored on the true object: `success` when it ends within 1 cm of the
    place location, upright and released (neither finger touching it); `place_error` [m];
    `approach_disturbance` [m], how far the object moved before the fingers began to close
    (the approach must not touch it); `grasped`, both fingers on it when the carry began;
    `time_to_place` [s], when the controller finished (None if it did not)."""
    pick, place = robot.grasp_layout(scenario)
    xy = np.column_stack([signals["object1_x"], signals["object1_y"]])
    left, right = (
        np.asarray(signals["finger_force_left"]),
        np.asarray(signals["finger_force_right"]),
    )
    closing = np.nonzero(phase == PHASE["grasping"])[0]
    before = closing[0] if closing.size else len(t)
    disturbance = float(np.max(np.linalg.norm(xy[:before] - np.array(pick), axis=1), initial=0.0))
    carry = np.nonzero((phase == PHASE["moving"]) & (np.arange(len(t)) > before))[0]
    grasped = bool(carry.size and left[carry[0]] > 0.0 and right[carry[0]] > 0.0)
    place_error = float(np.linalg.norm(xy[-1] - np.array(place)))
    upright = bool(np.asarray(signals["object1_upright"])[-1] == 1.0)
    released = bool(left[-1] == 0.0 and right[-1] == 0.0)
    done = np.nonzero(phase == PHASE["done"])[0]
    return {
        "success": place_error <= PLACE_TOLERANCE and upright and released,
        "place_error": place_error,
        "upright": upright,
        "released": released,
        "grasped": grasped,
        "approach_disturbance": disturbance,
        "time_to_place": float(t[done[0]]) if done.size else None,
        "pick": [float(v) for v in pick],
        "place": [float(v) for v in place],
    }


def settle_timeouts(
    t: np.ndarray, leg: np.ndarray, phase: np.ndarray, max_time: float, period: float
) -> list[dict[str, Any]]:
    """The grasp controller's settling phases that ended by `max_time` [s] instead of their
    condition, from its recorded TaskState (leg in `target_index`, `phase`): each a stretch of
    `settling` rows on one leg that a change ended after at least max_time (half a control
    `period` [s] of slack for the recording's rows); a stretch still running when the
    recording ends is not counted. Each: {"leg": its name, "start", "end" [s]}."""
    settling = phase == PHASE["settling"]
    timeouts = []
    start: int | None = None
    for row in range(len(t)):
        if start is not None and not (settling[row] and leg[row] == leg[start]):
            if t[row] - t[start] >= max_time - 0.5 * period:
                code = int(leg[start])
                timeouts.append(
                    {
                        "leg": LEGS[code] if 0 <= code < len(LEGS) else str(code),
                        "start": float(t[start]),
                        "end": float(t[row]),
                    }
                )
            start = None
        if settling[row] and start is None:
            start = row
    return timeouts


def _pipe(
    goal: tuple[float, float],
    segments: int,
    t: np.ndarray,
    tips: np.ndarray,
    signals: Mapping[str, Any],
    task: Any,
) -> dict[str, Any]:
    """Confined space: how deep the arm went into the walls (the Environment FMU's penetration
    of every segment), the contact impulse, and whether and when the true tip reached the goal
    (within `band` of it, and stayed)."""
    penetration = np.column_stack([signals[f"penetration_{n}"] for n in range(1, segments + 1)])
    error = np.linalg.norm(tips - np.array(goal), axis=1)
    finite = np.isfinite(error)
    outside = np.nonzero(~(error[finite] <= task.band))[0]
    times = t[finite]
    if outside.size == 0:
        reached_at: float | None = float(times[0]) if times.size else None
    elif outside[-1] + 1 < times.size:
        reached_at = float(times[outside[-1] + 1])
    else:
        reached_at = None
    impulse = np.asarray(signals["contact_impulse"])
    return {
        "penetration_max": float(np.nanmax(penetration)),
        "contact_impulse": float(impulse[np.isfinite(impulse)][-1]) if impulse.size else 0.0,
        "goal_reached": reached_at is not None,
        "time_to_goal": reached_at,
        "goal_error": float(error[finite][-1]) if finite.any() else None,
        "success": reached_at is not None,
    }


def _point_to_point(
    targets: tuple[tuple[float, float], ...],
    t: np.ndarray,
    tips: np.ndarray,
    index: np.ndarray,
    phase: np.ndarray,
    task: Any,
) -> dict[str, Any]:
    """Per target its error, time to settle and whether it settled (module docstring); over
    the targets their statistics, with a warning if the run ended before some were reached."""
    per_target = [
        _target(k, target, t, tips, index, phase, task) for k, target in enumerate(targets)
    ]
    reached = [e for e in per_target if e["reached"]]
    settled = sum(1 for e in reached if e["settled"])
    never = [k for k, e in enumerate(per_target) if not e["reached"]]
    warned = (
        [
            f"{len(never)} of {len(targets)} targets never reached (the first of them: number "
            f"{never[0] + 1}): the run ended first; lengthen duration or give fewer targets"
        ]
        if never
        else []
    )
    return {
        **_reached_statistics(reached),
        "targets": len(targets),
        "targets_settled": settled,
        "success": settled == len(targets),
        "per_target": per_target,
        "task_warnings": warned,  # summary.json's warnings
    }


def _reached_statistics(reached: list[dict[str, Any]]) -> dict[str, float | None]:
    """The error over the targets reached (mean, standard deviation, maximum) and their time
    to settle (mean over those that settled, maximum only if every one did); None without."""
    errors = np.array([e["error"] for e in reached])
    settle_times = [e["time_to_settle"] for e in reached if e["time_to_settle"] is not None]
    return {
        "tip_error_mean": float(np.mean(errors)) if errors.size else None,
        "tip_error_std": float(np.std(errors)) if errors.size else None,
        "tip_error_max": float(np.max(errors)) if errors.size else None,
        "time_to_settle": float(np.mean(settle_times)) if settle_times else None,
        "time_to_settle_max": (
            max(settle_times) if settle_times and len(settle_times) == len(reached) else None
        ),
    }


def _target(
    k: int,
    target: tuple[float, float],
    t: np.ndarray,
    tips: np.ndarray,
    index: np.ndarray,
    phase: np.ndarray,
    task: Any,
) -> dict[str, Any]:
    """Target `k`'s entry: whether the controller reached it (pursued it in an on-target
    phase) and then its mean error over the last `settle_time`, final error, time to settle,
    whether it reported it settled, and when it started on it."""
    rows = (index == k) & np.isin(phase, ON_TARGET_PHASES)
    entry: dict[str, Any] = {"target": [target[0], target[1]], "reached": bool(rows.any())}
    if rows.any():
        tk, error = t[rows], np.linalg.norm(tips[rows] - np.array(target), axis=1)
        window = tk >= tk[-1] - task.settle_time + 1e-9
        entry.update(
            error=float(np.mean(error[window])),
            final_error=float(error[-1]),
            time_to_settle=_time_to_settle(tk, error, task.band),
            settled=bool(np.any(phase[rows] == PHASE["settled"])),
            start=float(tk[0]),
        )
    return entry


def _time_to_settle(tk: np.ndarray, error: np.ndarray, band: float) -> float | None:
    """From the target's start `tk[0]` until the tip enters and stays within `band` of it
    [s]; None if it never does."""
    outside = np.nonzero(error > band)[0]
    if outside.size == 0:
        return 0.0
    if outside[-1] + 1 < tk.size:
        return float(tk[outside[-1] + 1] - tk[0])
    return None  # never within the band


def _paths(
    starts: tuple[tuple[float, float], ...],
    ends: tuple[tuple[float, float], ...],
    t: np.ndarray,
    tips: np.ndarray,
    index: np.ndarray,
    phase: np.ndarray,
    task: Any,
) -> dict[str, Any]:
    per_path = []
    distances = []
    for k, (a, b) in enumerate(zip(starts, ends, strict=True)):
        rows = (index == k) & (phase == PHASE["tracking"])
        entry: dict[str, Any] = {"start": list(a), "end": list(b), "tracked": bool(rows.any())}
        if rows.any():
            d = point_to_segment(tips[rows], np.array(a), np.array(b))
            distances.append(d)
            after = (index == k) & np.isin(phase, (PHASE["settling"], PHASE["settled"]))
            after &= t > t[rows][-1]
            end_error = np.linalg.norm(tips[after] - np.array(b), axis=1) if after.any() else None
            entry.update(
                rms=float(np.sqrt(np.mean(d**2))),
                max=float(np.max(d)),
                end_error=float(end_error[-1]) if end_error is not None else None,
                settled=bool(np.any(phase[index == k] == PHASE["settled"])),
            )
        per_path.append(entry)
    every = np.concatenate(distances) if distances else np.array([])
    tracked = [e for e in per_path if e["tracked"]]
    return {
        "path_rms": float(np.sqrt(np.mean(every**2))) if every.size else None,
        "path_max": float(np.max(every)) if every.size else None,
        "paths": len(starts),
        "paths_tracked": len(tracked),
        "success": len(tracked) == len(starts) and all(e["settled"] for e in tracked),
        "per_path": per_path,
    }


def draw_arm(robot: PlanarArm, scenario: Scenario, signals: Mapping[str, Any], path: Path) -> None:
    """The arm's true shapes over the run (darker is later), the true tip's trace, and the
    targets or paths, seen from above."""
    import io

    import matplotlib.pyplot as plt

    from hil.results import write_file

    plan = robot.task_plan(scenario)
    assert plan is not None
    lengths = [p["length"] for p in robot.parameters(scenario, "segment")]
    base = scenario.robot.base
    t = np.asarray(signals["time"])
    kappas = np.column_stack([signals[f"kappa_{n}"] for n in range(1, scenario.robot.segments + 1)])
    tips = true_tips(robot, scenario, signals)
    fig, ax = plt.subplots(figsize=(7, 7))
    colours = plt.get_cmap("viridis")
    span = max(float(t[-1] - t[0]), 1e-9) if t.size else 1.0
    for row in np.linspace(0, len(t) - 1, SHAPES).astype(int):  # the arm on its way, faint
        shape = kinematics.backbone(kappas[row], lengths, base)
        ax.plot(shape[:, 0], shape[:, 1], color=colours((t[row] - t[0]) / span), lw=1, alpha=0.35)
    phase = np.asarray(signals["phase"])
    for row in np.nonzero((phase == PHASE["settled"]) | (phase == PHASE["tracking"]))[0]:
        if phase[row] == PHASE["tracking"] and row % 50:  # every 0.5 s along a path
            continue
        shape = kinematics.backbone(kappas[row], lengths, base)  # settled shapes, bold
        ax.plot(shape[:, 0], shape[:, 1], color=colours((t[row] - t[0]) / span), lw=2.2)
    ax.plot(tips[:, 0], tips[:, 1], color="grey", lw=0.8, label="tip (true)")
    for k, wall in enumerate(plan.walls):
        xy = np.array(wall)
        ax.plot(xy[:, 0], xy[:, 1], color="saddlebrown", lw=3, label="walls" if k == 0 else None)
    grasp = robot.grasp_layout(scenario) if plan.kind == "grasp" else None
    draw_plan(ax, plan, grasp)
    if grasp is not None:
        trail = np.column_stack([signals["object1_x"], signals["object1_y"]])
        ax.plot(trail[:, 0], trail[:, 1], color="tab:blue", lw=1.2, label="object (true)")
        ax.add_patch(plt.Circle(trail[-1], plan.object_radius, color="tab:blue", alpha=0.5))
    ax.plot(base[0], base[1], "ks", ms=8, label="base")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    sm = plt.cm.ScalarMappable(cmap=colours, norm=plt.Normalize(t[0], t[-1] if t.size else 1.0))
    fig.colorbar(sm, ax=ax, label="time [s]", shrink=0.8)
    ax.set_title(f"{scenario.name}: arm shapes over time")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    image = io.BytesIO()
    fig.savefig(image, format="png", dpi=110)
    plt.close(fig)
    write_file(path, image.getvalue())


def draw_plan(
    ax: Any,
    plan: TaskPlan,
    grasp: tuple[tuple[float, float], tuple[float, float]] | None = None,
) -> None:
    """The task on `ax`: numbered targets, path lines, a pipe's goal, or a grasp's object start
    and place location (`grasp`: (pick, place) [m])."""
    from matplotlib.patches import Circle

    if plan.kind == "grasp" and grasp is not None:
        pick, place = grasp
        ax.add_patch(
            Circle(
                pick,
                plan.object_radius,
                fill=False,
                color="tab:blue",
                ls="--",
                label="object, start",
            )
        )
        ax.add_patch(Circle(place, 0.01, fill=False, color="red", label="place (1 cm)"))
    elif plan.kind == "pipe":
        ax.plot(*plan.targets[0], "r*", ms=14, label="goal")
    elif plan.kind == "point_to_point":
        for k, (x, y) in enumerate(plan.targets):
            ax.plot(x, y, "rx", ms=9, mew=2, label="targets" if k == 0 else None)
            ax.annotate(str(k), (x, y), textcoords="offset points", xytext=(5, 5), color="red")
    elif plan.kind == "path":
        for k, (a, b) in enumerate(zip(plan.targets, plan.ends, strict=True)):
            ax.plot(
                [a[0], b[0]],
                [a[1], b[1]],
                "r-",
                lw=2.5,
                alpha=0.6,
                label="paths" if k == 0 else None,
            )
            ax.plot(*a, "ro", ms=5)
