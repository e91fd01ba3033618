"""The spatial arm's figures: `arm.png`, 3-D snapshots of the true arm (its backbone from the
recorded bends) at the start and where each goal was declared settled, with the goals, the object
or the curve, and a sample of the statically reachable envelope; and `--animate` in 3-D.

Drawn with gravity pointing down the figure: the base frame turned by `display_rotation`
(horizontal base: the arm reaches along the figure's x; hanging: down its z).
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hil.animation import DPI, frame_rows, playback_fps, write_animation
from hil.results import write_file

if TYPE_CHECKING:
    from hil.scenario import Scenario
    from robots.spatial_arm.plant.rig import SpatialArm

ENVELOPE_POINTS = 400  # envelope samples drawn (light dots)


def display_rotation(base: str) -> np.ndarray:
    """Base frame to the figure's frame (z up): gravity along the figure's -z."""
    if base == "down":
        return np.diag([1.0, -1.0, -1.0])
    return np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


def _backbones(arm: SpatialArm, scenario: Scenario, signals: Mapping[str, Any], rows: Any) -> Any:
    from robots.spatial_arm.controller import kinematics
    from robots.spatial_arm.plant.metrics import bends

    model = arm.model(scenario)
    n = scenario.robot.segments
    qs = np.array([bends(signals, n, int(k)) for k in rows])
    return kinematics.backbone(model, qs, 12) @ display_rotation(scenario.robot.pose).T


def _task_points(arm: SpatialArm, scenario: Scenario) -> tuple[np.ndarray, str]:
    plan = arm.task_layout(scenario)
    rotation = display_rotation(scenario.robot.pose)
    if scenario.task.kind == "confined":
        return np.asarray(scenario.robot.pipe) @ rotation.T, "pipe axis"
    if plan.curve:
        return np.asarray(plan.curve) @ rotation.T, "curve"
    if plan.object is not None:
        goal = np.asarray(plan.object) + np.asarray(scenario.robot.offset)
        return np.vstack([plan.object, goal]) @ rotation.T, "object, goal"
    if plan.goals:
        return np.asarray(plan.goals) @ rotation.T, "goals"
    return np.zeros((0, 3)), ""


def _axes(fig: Any, points: np.ndarray, title: str) -> Any:
    ax = fig.add_subplot(projection="3d")
    low, high = points.min(axis=0), points.max(axis=0)
    centre, half = 0.5 * (low + high), 0.5 * float(np.max(high - low)) + 0.02
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
        setter(c - half, c + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m] (up)")
    ax.set_title(title, fontsize=9)
    return ax


def draw_arm(arm: SpatialArm, scenario: Scenario, signals: Mapping[str, Any], path: Path) -> None:
    from matplotlib.figure import Figure

    from robots.spatial_arm.plant.metrics import SETTLED, windows

    phase = np.nan_to_num(np.asarray(signals["phase"], dtype=float))
    rows = [0]
    for _, start, end in windows(signals):
        declared = np.flatnonzero(phase[start : end + 1] == SETTLED)
        rows.append(start + int(declared[0]) if declared.size else end)
    if len(signals["time"]) - 1 not in rows:
        rows.append(len(signals["time"]) - 1)
    lines = _backbones(arm, scenario, signals, rows)
    task, label = _task_points(arm, scenario)
    from robots.spatial_arm.plant.task import draw_equilibria

    cloud = draw_equilibria(arm, scenario, ENVELOPE_POINTS, 99)
    from robots.spatial_arm.controller import kinematics

    envelope = kinematics.tip(arm.model(scenario), cloud) @ display_rotation(scenario.robot.pose).T
    fig = Figure(figsize=(7.0, 6.5), dpi=DPI, layout="constrained")
    every = np.vstack([lines.reshape(-1, 3), task.reshape(-1, 3), envelope])
    ax = _axes(fig, every, f"{scenario.name}: the arm at the start and at each settled goal")
    ax.scatter(*envelope.T, s=2, color="0.75", label="reachable tips (sample)")
    colours = ["tab:grey"] + [f"C{k % 10}" for k in range(len(lines) - 1)]
    for k, (line, colour) in enumerate(zip(lines, colours, strict=True)):
        ax.plot(*line.T, "-", color=colour, lw=2.0, label="start" if k == 0 else None)
        ax.scatter(*line[-1], color=colour, s=12)
    if len(task):
        style = "-" if label in ("curve", "pipe axis") else "none"
        ax.plot(*task.T, marker="x", ls=style, color="black", ms=7, label=label)
    ax.scatter(0, 0, 0, marker="s", color="black", s=30, label="base")
    fig.legend(loc="outside lower center", ncols=4, fontsize=7)
    image = io.BytesIO()
    fig.savefig(image, format="png", dpi=110)
    write_file(path, image.getvalue())  # whole or not at all, like every results file


def animate_arm(
    arm: SpatialArm, scenario: Scenario, signals: Mapping[str, Any], path: Path, fmt: str
) -> None:
    from matplotlib.figure import Figure

    t = np.asarray(signals["time"])
    rows = frame_rows(t)
    lines = _backbones(arm, scenario, signals, rows)
    task, label = _task_points(arm, scenario)
    fig = Figure(figsize=(6.0, 6.0), dpi=DPI, layout="constrained")
    every = np.vstack([lines.reshape(-1, 3), task.reshape(-1, 3)])
    ax = _axes(fig, every, f"{scenario.name}: the spatial arm")
    if len(task):
        ax.plot(*task.T, marker="x", ls="none", color="black", label=label)
    (body,) = ax.plot([], [], [], "-", color="tab:blue", lw=2.5, label="arm")
    stamp = ax.text2D(0.02, 0.97, "", transform=ax.transAxes, va="top", family="monospace")

    def update(k: int) -> None:
        line = lines[k]
        body.set_data_3d(line[:, 0], line[:, 1], line[:, 2])
        stamp.set_text(f"t = {t[rows[k]]:6.3f} s")

    fig.legend(loc="outside lower center", ncols=3, fontsize=7)
    write_animation(fig, [body, stamp], update, rows.size, playback_fps(t, rows), path, fmt)


def draw_confining(summary_rows: list[dict[str, float]], name: str, path: Path) -> None:
    """The minimum confining radius against the pipe's bend radius, soft and rigid-link."""
    from matplotlib.figure import Figure

    R = np.array([row["bend_radius"] for row in summary_rows])
    soft = np.array([row["soft"] for row in summary_rows])
    rigid = np.array([row["rigid"] for row in summary_rows])
    fig = Figure(figsize=(6.5, 4.0), dpi=DPI, layout="constrained")
    ax = fig.add_subplot()
    ax.plot(R * 1e3, soft * 1e3, "o-", color="tab:blue", label="soft arm (continuous bend)")
    ax.plot(R * 1e3, rigid * 1e3, "s--", color="tab:red", label="rigid-link arm, same reach")
    ax.set_xlabel("pipe bend radius [mm]")
    ax.set_ylabel("minimum confining radius [mm]")
    ax.set_title(f"{name}: the confining space each arm needs", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    image = io.BytesIO()
    fig.savefig(image, format="png", dpi=110)
    write_file(path, image.getvalue())
