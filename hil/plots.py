"""PNG plots of a run, one per plot spec of the robot: a panel per actuator, a line per column."""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - after choosing the headless backend
import numpy as np  # noqa: E402

from hil.results import write_file  # noqa: E402
from hil.rig import PlotSpec  # noqa: E402

# Fixed margins of a stacked-panel figure [in]: room for two-line y labels, the shared x axis's
# ticks and label. `tight_layout` measured every text to find them: 0.2-0.5 s per figure, half of
# a 6-segment run's plotting.
MARGIN_LEFT, MARGIN_RIGHT, MARGIN_TOP, MARGIN_BOTTOM, PANEL_GAP = 0.95, 0.15, 0.15, 0.5, 0.25


def stack_layout(fig: plt.Figure) -> None:
    """Place a figure's vertically stacked panels (shared x) with the fixed margins."""
    width, height = fig.get_size_inches()
    rows = len(fig.axes)
    panel = (height - MARGIN_TOP - MARGIN_BOTTOM - PANEL_GAP * (rows - 1)) / rows
    fig.subplots_adjust(
        left=MARGIN_LEFT / width,
        right=1.0 - MARGIN_RIGHT / width,
        top=1.0 - MARGIN_TOP / height,
        bottom=MARGIN_BOTTOM / height,
        hspace=PANEL_GAP / panel,
    )


def plot_run(signals: Mapping[str, np.ndarray], specs: Sequence[PlotSpec], out: Path) -> list[Path]:
    """Write `<spec.name>.png` for every spec; returns their paths."""
    t = signals["time"]
    written = []
    for spec in specs:
        count = len(spec.panels)
        fig, axes = plt.subplots(
            count, 1, figsize=(9, 2.6 * count + 0.6), sharex=True, squeeze=False
        )
        for i, title in enumerate(spec.panels, start=1):
            ax = axes[i - 1][0]
            for template, label, scale, style in spec.lines:
                column = template.format(n=i)
                if column in signals:
                    ax.plot(t, signals[column] * scale, label=label, **style)
            ax.set_ylabel(f"{title}\n{spec.ylabel}")
            ax.grid(True, alpha=0.3)
            ax.legend(loc="upper right", fontsize=8)
        axes[-1][0].set_xlabel("time [s]")
        stack_layout(fig)
        path = out / f"{spec.name}.png"
        image = io.BytesIO()
        fig.savefig(image, format="png", dpi=110)
        plt.close(fig)
        write_file(path, image.getvalue())  # whole or not at all, like every results file
        written.append(path)
    return written
