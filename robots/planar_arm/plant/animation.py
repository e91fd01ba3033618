"""The planar arm's animation (`hil run --animate`): one run seen from above, frame by frame.

Each frame draws what `arm_frame` returns for one recorded row: the true backbone (forward
kinematics of the recorded true curvatures `kappa_n`), the gripper's fingers where the run
recorded their bend angle (`gripper_theta`; robots.planar_arm.controller.gripper.finger_points at
the true tip
pose), and the disk objects where the Environment FMU put them (`object{o}_x`, `object{o}_y`).
Around them stays what does not move: the channel walls (`[robot.environment] walls`), the
task's targets, lines or goal (as `planar_tasks.draw_arm` draws them), the base; and the tip's
trace so far, the controller's task-space reference point where it reported one, a time stamp.

To draw more (a grasped object, contact forces), extend `ArmFrame` and `arm_frame`, and the
artists `animate_arm` updates from them. Invariant: a frame is the recorded truth at its row; no
frame interpolates or estimates.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from controllers import kinematics
from hil.animation import (
    DPI,
    figure_size,
    frame_rows,
    playback_fps,
    top_view,
    write_animation,
)
from robots.planar_arm.controller.gripper import GripperGeometry, finger_points
from robots.planar_arm.plant import environment, gripper

if TYPE_CHECKING:
    from hil.scenario import Scenario
    from robots.planar_arm.controller.tasks import TaskPlan
    from robots.planar_arm.plant.rig import PlanarArm

BACKBONE_POINTS = 8  # per segment: smooth enough at this size
MARGIN = 0.02  # [m] around everything drawn


@dataclass(frozen=True)
class ArmScene:
    """What stays put over a run: the arm's geometry, its world and its task [m, rad]."""

    name: str
    lengths: tuple[float, ...]
    base: tuple[float, float, float]
    walls: tuple[np.ndarray, ...] = ()  # polylines, each shape (vertices, 2)
    object_radii: tuple[float, ...] = ()  # one per object, in the order of `object{o}_*`
    plan: TaskPlan | None = None
    gripper: GripperGeometry = field(default_factory=GripperGeometry)
    grasp: tuple[tuple[float, float], tuple[float, float]] | None = None  # (pick, place) [m]


@dataclass(frozen=True)
class ArmFrame:
    """What one frame draws, at one recorded instant [s, m].

    `backbone` has shape (points, 2), base first; `fingers` holds one polyline (shape (points,
    2)) per finger, none without a gripper; `objects` is one (x, y, radius) per disk, in the
    scene's order (a NaN centre where it was not recorded: drawn nowhere); `reference` is the
    controller's task-space reference point, None where it reported none."""

    time: float
    backbone: np.ndarray
    fingers: tuple[np.ndarray, ...] = ()
    objects: tuple[tuple[float, float, float], ...] = ()
    reference: tuple[float, float] | None = None


def arm_scene(robot: PlanarArm, scenario: Scenario) -> ArmScene:
    """The scene of a planar-arm scenario: segment lengths, base, walls, the objects' radii (as
    the Environment FMU has them, task-placed objects included), the plan, the fingers'
    geometry (`[robot.gripper]`), a grasp task's pick and place."""
    world = scenario.robot.environment
    radii: tuple[float, ...] = ()
    if environment.present(scenario):
        values = robot.environment_parameters(scenario)
        count = int(values.get("n_objects", 0))
        radii = tuple(values[f"object_radius_{o}"] for o in range(1, count + 1))
    plan = robot.task_plan(scenario)
    return ArmScene(
        name=scenario.name,
        lengths=tuple(p["length"] for p in robot.parameters(scenario, "segment")),
        base=tuple(scenario.robot.base),  # type: ignore[arg-type]
        walls=tuple(np.array(wall, dtype=float) for wall in world.get("walls", [])),
        object_radii=radii,
        plan=plan,
        gripper=gripper.geometry(scenario) if gripper.present(scenario) else GripperGeometry(),
        grasp=robot.grasp_layout(scenario) if plan is not None and plan.kind == "grasp" else None,
    )


def arm_frame(scene: ArmScene, signals: Mapping[str, Any], row: int) -> ArmFrame:
    """The shapes of recorded row `row`: the backbone from the true curvatures, the fingers
    where `gripper_theta` is recorded (at the tip pose of the same curvatures), the objects at
    their recorded positions, the reported reference point."""
    kappas = [float(signals[f"kappa_{n}"][row]) for n in range(1, len(scene.lengths) + 1)]
    backbone = kinematics.backbone(kappas, scene.lengths, scene.base, BACKBONE_POINTS)
    fingers: tuple[np.ndarray, ...] = ()
    theta = float(signals["gripper_theta"][row]) if "gripper_theta" in signals else np.nan
    if np.isfinite(theta):
        tip = kinematics.forward(kappas, scene.lengths, scene.base)[-1]
        fingers = finger_points(scene.gripper, (tip[0], tip[1], tip[2]), theta)
    objects = []
    for o, radius in enumerate(scene.object_radii, start=1):
        x, y = signals.get(f"object{o}_x"), signals.get(f"object{o}_y")
        if x is None or y is None:  # not recorded: nowhere (a NaN centre draws nothing)
            objects.append((np.nan, np.nan, radius))
        else:
            objects.append((float(x[row]), float(y[row]), radius))
    reference = None
    if "target_x" in signals and "target_y" in signals:
        rx, ry = float(signals["target_x"][row]), float(signals["target_y"][row])
        if np.isfinite(rx) and np.isfinite(ry):
            reference = (rx, ry)
    return ArmFrame(
        time=float(signals["time"][row]),
        backbone=backbone[:, :2],
        fingers=tuple(fingers),
        objects=tuple(objects),
        reference=reference,
    )


def animate_arm(
    robot: PlanarArm,
    scenario: Scenario,
    signals: Mapping[str, Any],
    path: Path,
    fmt: str,
    frame: Callable[[ArmScene, Mapping[str, Any], int], ArmFrame] = arm_frame,
) -> None:
    """Write the run's animation to `path` (`fmt`: "gif" or "mp4"); see the module docstring."""
    scene = arm_scene(robot, scenario)
    t = np.asarray(signals["time"])
    rows = frame_rows(t)
    frames = [frame(scene, signals, int(row)) for row in rows]
    # the tip's trace: every recorded row, not only the frames' (a frame shows all of it so far)
    kappas = np.column_stack([signals[f"kappa_{n}"] for n in range(1, len(scene.lengths) + 1)])
    tips = np.array([kinematics.forward(k, scene.lengths, scene.base)[-1, :2] for k in kappas])
    fig, moving, update = _figure(scene, frames, tips.reshape(-1, 2), rows)
    write_animation(fig, moving, update, len(frames), playback_fps(t, rows), path, fmt)


def _figure(
    scene: ArmScene, frames: list[ArmFrame], tips: np.ndarray, rows: np.ndarray
) -> tuple[Any, list[Any], Callable[[int], None]]:
    """The figure with everything that stays put, its moving artists, and the update of frame
    k. Lines for fingers, disks and the reference exist only where some frame has them."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    low, high = _bounds(scene, frames, tips)
    fig = Figure(figsize=figure_size(low, high), dpi=DPI, layout="constrained")
    ax = fig.add_subplot()
    for k, wall in enumerate(scene.walls):
        ax.plot(
            wall[:, 0], wall[:, 1], color="saddlebrown", lw=3, label="walls" if k == 0 else None
        )
    _draw_plan(ax, scene)
    ax.plot(scene.base[0], scene.base[1], "ks", ms=8, label="base")
    (trace,) = ax.plot([], [], color="grey", lw=0.8, label="tip (true)")
    (arm,) = ax.plot([], [], "-", color="tab:blue", lw=3, solid_capstyle="round", label="arm")
    (joints,) = ax.plot([], [], "o", color="navy", ms=3.5)
    fingers = [
        ax.plot([], [], "-", color="tab:green", lw=2.5, label=None if i else "fingers")[0]
        for i in range(max(len(f.fingers) for f in frames))
    ]
    disks: list[Circle] = [
        ax.add_patch(  # type: ignore[misc]
            Circle(
                (np.nan, np.nan), 0.0, color="tab:orange", alpha=0.7, label=None if o else "objects"
            )
        )
        for o in range(max(len(f.objects) for f in frames))
    ]
    references = [
        ax.plot([], [], "+", color="red", ms=10, mew=1.5, label="reference")[0]
        for _ in range(any(f.reference is not None for f in frames))
    ]
    stamp = top_view(ax, low, high, f"{scene.name}: the arm from above", 6)

    def update(k: int) -> None:
        f = frames[k]
        arm.set_data(f.backbone[:, 0], f.backbone[:, 1])
        ends = f.backbone[::BACKBONE_POINTS]  # the base and every segment's end
        joints.set_data(ends[:, 0], ends[:, 1])
        trace.set_data(tips[: rows[k] + 1, 0], tips[: rows[k] + 1, 1])
        for i, line in enumerate(fingers):
            points = f.fingers[i] if i < len(f.fingers) else np.zeros((0, 2))
            line.set_data(points[:, 0], points[:, 1])
        for o, disk in enumerate(disks):
            x, y, radius = f.objects[o] if o < len(f.objects) else (np.nan, np.nan, 0.0)
            disk.set_center((x, y))
            disk.set_radius(radius)
        for line in references:
            line.set_data(*(([f.reference[0]], [f.reference[1]]) if f.reference else ([], [])))
        stamp.set_text(f"t = {f.time:6.2f} s")

    moving = [trace, arm, joints, *fingers, *disks, *references, stamp]
    return fig, moving, update


def _draw_plan(ax: Any, scene: ArmScene) -> None:
    """The task's targets, lines, goal or pick and place, as planar_tasks.draw_arm draws them."""
    from robots.planar_arm.plant.tasks import draw_plan

    if scene.plan is not None:
        draw_plan(ax, scene.plan, scene.grasp)


def _bounds(
    scene: ArmScene, frames: list[ArmFrame], tips: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Fixed axes (lower left, upper right corner [m]) around everything any frame draws, so
    the view never jumps."""
    points = [np.array([scene.base[:2]]), tips.reshape(-1, 2), *scene.walls]
    for f in frames:
        points.append(f.backbone)
        points += list(f.fingers)
        points += [np.array([[x - r, y - r], [x + r, y + r]]) for x, y, r in f.objects]
    if scene.plan is not None:
        points.append(np.array(scene.plan.targets + scene.plan.ends).reshape(-1, 2))
    if scene.grasp is not None:
        points.append(np.array(scene.grasp))
    every = np.vstack(points)
    every = every[np.all(np.isfinite(every), axis=1)]
    return every.min(axis=0) - MARGIN, every.max(axis=0) + MARGIN
