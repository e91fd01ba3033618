"""PNG plots of a run: curvature (reference, controller estimate, truth), pressures, pistons."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - after choosing the headless backend

from hil.summary import read_signals  # noqa: E402


def plot_run(signals_path: Path, segments: int, out: Path) -> list[Path]:
    """Write curvature.png, pressures.png and piston.png; returns their paths."""
    s = read_signals(signals_path)
    t = s["time"]
    written = []

    def figure(name: str, ylabel: str, series: list[tuple[str, str, float, dict]]) -> None:
        fig, axes = plt.subplots(
            segments, 1, figsize=(9, 2.6 * segments + 0.6), sharex=True, squeeze=False
        )
        for i in range(1, segments + 1):
            ax = axes[i - 1][0]
            for column, label, scale, style in series:
                ax.plot(t, s[f"{column}_{i}"] * scale, label=label, **style)
            ax.set_ylabel(f"segment {i}\n{ylabel}")
            ax.grid(True, alpha=0.3)
            ax.legend(loc="upper right", fontsize=8)
        axes[-1][0].set_xlabel("time [s]")
        fig.tight_layout()
        path = out / f"{name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)

    figure(
        "curvature",
        "curvature [1/m]",
        [
            ("kappa_ref", "reference", 1.0, {"color": "black", "linestyle": "--"}),
            ("kappa_est", "estimate (controller)", 1.0, {"color": "tab:orange"}),
            ("kappa", "true", 1.0, {"color": "tab:blue", "alpha": 0.8}),
        ],
    )
    figure(
        "pressures",
        "gauge pressure [kPa]",
        [
            ("p_a", "side a", 1e-3, {"color": "tab:red"}),
            ("p_b", "side b", 1e-3, {"color": "tab:green"}),
        ],
    )
    figure(
        "piston",
        "piston [mm]",
        [
            ("x_ref", "setpoint", 1e3, {"color": "black", "linestyle": "--"}),
            ("x", "position", 1e3, {"color": "tab:purple"}),
        ],
    )
    return written
