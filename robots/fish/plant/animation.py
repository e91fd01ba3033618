"""The soft fish's animation (`hil run --animate`): its body seen from above, frame by frame.

Each frame draws the recorded outline (nose, head-tail joint, the ends of the three tail pieces:
columns `nose_x/_y`, `x/_y`, `tail_{j}_x/_y`), the joint's path so far and a time stamp, at the
rows `hil.animation.frame_rows` picks. Invariant: a frame is the recorded truth at its row.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from hil.animation import (
    DPI,
    figure_size,
    frame_rows,
    playback_fps,
    top_view,
    write_animation,
)

MARGIN = 0.03  # [m] around the fish's whole way


def outline(signals: Mapping[str, Any]) -> np.ndarray:
    """The body's outline at every row, shape (rows, 5, 2) [m]: nose, joint, tail ends 1-3."""
    names = ["nose", None, "tail_1", "tail_2", "tail_3"]
    columns = [
        np.column_stack(
            [signals["x" if n is None else f"{n}_x"], signals["y" if n is None else f"{n}_y"]]
        )
        for n in names
    ]
    return np.stack(columns, axis=1)


def animate_fish(name: str, signals: Mapping[str, Any], path: Path, fmt: str) -> None:
    """Write the run's animation to `path` (`fmt`: "gif" or "mp4"); see the module docstring."""
    from matplotlib.figure import Figure

    t = np.asarray(signals["time"])
    rows = frame_rows(t)
    body = outline(signals)
    every = body.reshape(-1, 2)
    every = every[np.all(np.isfinite(every), axis=1)]
    low, high = every.min(axis=0) - MARGIN, every.max(axis=0) + MARGIN
    fig = Figure(figsize=figure_size(low, high), dpi=DPI, layout="constrained")
    ax = fig.add_subplot()
    (path_so_far,) = ax.plot([], [], ":", color="grey", lw=1, label="joint path")
    (fish,) = ax.plot([], [], "-o", color="tab:blue", lw=2.5, ms=3, label="body")
    (nose,) = ax.plot([], [], "^", color="navy", ms=7, label="nose")
    stamp = top_view(ax, low, high, f"{name}: the fish from above", 3)

    def update(k: int) -> None:
        row = rows[k]
        fish.set_data(body[row, :, 0], body[row, :, 1])
        nose.set_data(body[row, :1, 0], body[row, :1, 1])
        path_so_far.set_data(body[: row + 1, 1, 0], body[: row + 1, 1, 1])
        stamp.set_text(f"t = {t[row]:6.3f} s")

    moving = [path_so_far, fish, nose, stamp]
    write_animation(fig, moving, update, rows.size, playback_fps(t, rows), path, fmt)
