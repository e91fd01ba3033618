"""The spatial arm's statically reachable envelope as `hil envelope` shows it: sampled from the
static model (robots.spatial_arm.controller.envelope), summarised, exported and drawn with
gravity down the figure, with the straight arm and its passive rest for scale."""

from __future__ import annotations

import io
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hil.results import write_file

if TYPE_CHECKING:
    from hil.scenario import Scenario
    from robots.spatial_arm.plant.rig import SpatialArm


def envelope(arm: SpatialArm, scenario: Scenario, samples: int | None = None) -> Any:
    from robots.spatial_arm.controller.envelope import sample_envelope

    n = samples if samples is not None else scenario.robot.envelope_samples
    return sample_envelope(arm.model(scenario), n, seed=scenario.seed)


def report(arm: SpatialArm, scenario: Scenario, found: Any) -> str:
    from robots.spatial_arm.controller import kinematics
    from robots.spatial_arm.plant.figures import display_rotation
    from robots.spatial_arm.plant.metrics import droop

    model = arm.model(scenario)
    up = (found.points @ display_rotation(scenario.robot.pose).T)[:, 2]
    rest = kinematics.tip(model, arm.start_bends(scenario))
    straight = kinematics.tip(model, np.zeros(model.n_q))
    low, high = found.points.min(axis=0), found.points.max(axis=0)
    return (
        f"{len(found.points)} static rests; tips within x [{low[0]:.3f}, {high[0]:.3f}], "
        f"y [{low[1]:.3f}, {high[1]:.3f}], z [{low[2]:.3f}, {high[2]:.3f}] m (base frame); "
        f"highest tip {1e3 * up.max():+.1f} mm, lowest {1e3 * up.min():+.1f} mm from the base "
        f"(up); passive droop {1e3 * droop(model, rest, straight):.1f} mm below the straight tip"
    )


def files(found: Any) -> dict[str, bytes]:
    """envelope.npz (tips, bends, pistons, the inside test's radius) and envelope.csv (tips)."""
    out: dict[str, bytes] = {}
    with tempfile.TemporaryDirectory(prefix="softhil-envelope-") as folder:
        for name in ("envelope.npz", "envelope.csv"):
            path = Path(folder) / name
            found.save(path)
            out[name] = path.read_bytes()
    return out


def draw(arm: SpatialArm, scenario: Scenario, found: Any, path: Path) -> None:
    from matplotlib.figure import Figure

    from robots.spatial_arm.controller import kinematics
    from robots.spatial_arm.plant.figures import display_rotation

    model = arm.model(scenario)
    turn = display_rotation(scenario.robot.pose).T
    tips = found.points @ turn
    rest = kinematics.backbone(model, arm.start_bends(scenario), 12) @ turn
    straight = kinematics.backbone(model, np.zeros(model.n_q), 12) @ turn
    fig = Figure(figsize=(7.0, 6.5), dpi=100, layout="constrained")
    ax = fig.add_subplot(projection="3d")
    every = np.vstack([tips, rest, straight])
    low, high = every.min(axis=0), every.max(axis=0)
    centre, half = 0.5 * (low + high), 0.5 * float(np.max(high - low)) + 0.02
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
        setter(c - half, c + half)
    ax.set_box_aspect((1, 1, 1))
    colour = tips[:, 2]
    ax.scatter(*tips.T, s=2, c=colour, cmap="viridis", label="reachable tips at rest")
    ax.plot(*straight.T, "--", color="black", lw=1.5, label="straight (no gravity)")
    ax.plot(*rest.T, "-", color="tab:red", lw=2.5, label="passive rest under gravity")
    ax.scatter(0, 0, 0, marker="s", color="black", s=30, label="base")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m] (up)")
    ax.set_title(f"{scenario.name}: statically reachable envelope ({len(tips)} rests)", fontsize=9)
    fig.legend(loc="outside lower center", ncols=2, fontsize=7)
    image = io.BytesIO()
    fig.savefig(image, format="png", dpi=110)
    write_file(path, image.getvalue())
