"""The estimation report: every estimator run over the same recorded measurements.

A run's CAN log holds everything the controller measured: the drive status frames (pressures)
and the camera's pictures (CameraFrame headers and marker frames) of every cycle. This module
rebuilds, cycle by cycle, exactly what the controller node handed its estimator (the pictures
due by each SYNC, assembled by content), runs `raw`, `kf` and `ukf` over it offline, and scores
each against the true curvature the plant recorded at the same SYNC. The result is
`summary.json`'s `estimation` section and `hil estimate RUN_DIR`; `estimation.png` shows truth,
measurement and estimates with the dropouts and rejected outliers marked, and the residuals of
the visible markers against the chosen estimate.
"""

from __future__ import annotations

import json
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.bustools.logs import has_direction
from hil.cycles import CSV_HAS_NO_DIRECTION, config_beside, read_cycles, read_log
from hil.errors import HilError
from hil.seam import (
    ESTIMATORS,
    ArmConfig,
    CameraAssembler,
    DriveReading,
    MarkerFrame,
    estimators,
    kinematics,
)
from hil.summary import read_signals
from rigbus.protocol import CameraFrame, CameraMarker, DriveStatus, Protocol

Cycle = tuple[float, dict[int, DriveReading], list[MarkerFrame]]


@dataclass(frozen=True)
class EstimatorScore:
    name: str
    kappa: np.ndarray  # (cycles, segments) [1/m]
    kappa_std: np.ndarray
    gated: np.ndarray  # (cycles,)
    measured: np.ndarray
    update_time: float  # mean wall time of one update [s]


def measured_cycles(log: Path, config: ArmConfig) -> list[Cycle]:
    """What the controller's estimator was given at every SYNC of a recorded run."""
    protocol = Protocol()
    cycles = read_cycles(read_log(log), protocol, str(log))
    timing = config.camera_timing
    assembler = CameraAssembler(timing.markers)
    taken = 0
    drives: dict[int, DriveReading] = {}
    result: list[Cycle] = []
    for cycle in cycles:
        t = cycle.index * config.control_period
        for message in cycle.plant:
            frame = protocol.decode(message)
            if isinstance(frame, DriveStatus):
                drives[frame.node] = DriveReading(
                    frame.piston_position, frame.p_a, frame.p_b, frame.fault
                )
            elif isinstance(frame, CameraFrame | CameraMarker):
                assembler.add(frame)
        due = timing.frames_due(cycle.index)
        frames = []
        for j in range(taken, due):
            if assembler.complete(j):
                picture = assembler.take(j, t)  # the arm's markers (objects' follow them)
                arm = picture.points[: len(config.lengths) + 1]
                frames.append(MarkerFrame(exposure_time=picture.exposure_time, points=arm))
            else:
                assembler.drop(j)
        taken = max(taken, due)
        result.append((t, dict(drives), frames))
    return result


def score(name: str, config: ArmConfig, cycles: list[Cycle]) -> EstimatorScore:
    estimator = estimators().make_estimator(
        name,
        config.bends,
        config.base,
        config.camera,
        config.control_period,
        config.latency_compensation,
    )
    kappa, std, gated, measured = [], [], [], []
    started = time.perf_counter()
    for t, drives, frames in cycles:
        estimate = estimator.update(t, drives, frames)
        kappa.append(estimate.kappa)
        std.append(estimate.kappa_std)
        gated.append(estimate.gated)
        measured.append(estimate.measured)
    elapsed = time.perf_counter() - started
    return EstimatorScore(
        name,
        np.array(kappa),
        np.array(std),
        np.array(gated),
        np.array(measured),
        elapsed / max(1, len(cycles)),
    )


@dataclass(frozen=True)
class RecordedRun:
    """What the estimation report reads from a run's folder, every part of it checked."""

    log: Path
    config: ArmConfig
    signals: dict[str, np.ndarray]
    truth: np.ndarray  # (cycles, segments) true curvature [1/m]
    cycles: list[Cycle]


def read_run(run: Path, log: Path | None = None) -> RecordedRun:
    """The recorded inputs of the estimation report of the run in `run` (its CAN log `log`, by
    default the one the run wrote, `_log_of`): HilError naming the file (and line) that is
    missing, damaged, of another robot kind, or a CSV log."""
    check_estimable(run, log)
    log = log or _log_of(run)
    config = config_beside(
        log,
        "hil estimate needs the run's controller configuration (estimator, camera, arm) to "
        "rebuild what its estimator was given",
    )
    if not isinstance(config, ArmConfig):
        raise HilError(
            f"{log.parent / 'controller.json'}: the estimation report applies to planar-arm "
            f"runs, not robot kind {getattr(config, 'robot', '?')!r}"
        )
    path = run / "signals.csv"
    signals = read_signals(path)
    for n in range(1, config.segments + 1):
        if f"kappa_{n}" not in signals:
            raise HilError(f"{path}: no column kappa_{n} (the true curvature of segment {n})")
    truth = np.column_stack([signals[f"kappa_{n}"] for n in range(1, config.segments + 1)])
    cycles = measured_cycles(log, config)
    if len(cycles) != len(truth):
        raise HilError(
            f"{run}: {len(cycles)} cycles in the CAN log but {len(truth)} rows in signals.csv"
        )
    return RecordedRun(log, config, signals, truth, cycles)


def estimation_report(
    run: Path, plot: bool = True, log: Path | None = None, recorded: RecordedRun | None = None
) -> dict[str, Any]:
    """Per estimator: `rms` and `max` curvature error against truth [1/m] over every cycle but
    the first (nothing is measured before the first picture arrives), `gated` (share of camera
    measurements rejected as outliers) and `update_time` [s]. The CAN log is `log`, by default
    the one the run in `run` wrote (`_log_of`); `recorded` is what `read_run` read, if it did."""
    recorded = recorded or read_run(run, log)
    config, signals, truth, cycles = (
        recorded.config,
        recorded.signals,
        recorded.truth,
        recorded.cycles,
    )
    scores = {name: score(name, config, cycles) for name in ESTIMATORS}
    report: dict[str, Any] = {"chosen": config.estimator}
    for name, s in scores.items():
        error = np.abs(s.kappa[1:] - truth[1:])
        considered = s.gated.sum() + s.measured.sum()
        report[name] = {
            "rms": float(np.sqrt(np.mean(error**2))),
            "max": float(np.max(error)),
            "gated": float(s.gated.sum() / considered) if considered else 0.0,
            "update_time": s.update_time,
        }
    if plot:
        _plot(run, config, signals, cycles, scores)
    return report


def check_estimable(run: Path, log: Path | None = None) -> None:
    """HilError unless the run in `run` is of a robot kind with this report (the planar arm's
    curvature estimators), as its scenario.toml says, or without one its controller.json (a
    folder with neither is taken for an arm); or if its CAN log (`log`, by default the one found
    there) is a CSV, which cannot tell the plant's frames from the controller's. Reads only."""
    from hil.rig import robot_kind

    kind, source = _robot_kind_of(run)
    if kind is not None and not getattr(robot_kind(kind), "estimation_report", True):
        raise HilError(
            f"{run}: the estimation report applies to planar-arm runs, not robot kind {kind!r} "
            f"({source})"
        )
    if log is None:
        try:
            log = _log_of(run)
        except HilError:
            return  # said when the report reads the log
    if not has_direction(log):
        raise HilError(f"{log}: hil estimate cannot use a .csv log: {CSV_HAS_NO_DIRECTION}")


def _robot_kind_of(run: Path) -> tuple[str | None, str]:
    """The robot kind of the run in `run` and the file that says so: its scenario.toml's
    [robot] kind, else its controller.json's `robot` (None where neither says)."""
    try:
        data = tomllib.loads((run / "scenario.toml").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        pass
    else:
        section = data.get("robot")
        kind = section.get("kind", "planar_arm") if isinstance(section, dict) else "planar_arm"
        return (kind if isinstance(kind, str) else None), "scenario.toml"
    try:
        data = json.loads((run / "controller.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None, "controller.json"
    kind = data.get("robot", "planar_arm") if isinstance(data, dict) else None
    return (kind if isinstance(kind, str) else None), "controller.json"


def _log_of(run: Path) -> Path:
    """The CAN log of the run in `run`: the one its summary.json names (a run's --can-log or
    [recording] can_log), else the first of the default names (can.log, can.blf, ...) there."""
    try:
        named = json.loads((run / "summary.json").read_text(encoding="utf-8")).get("can_log")
    except (OSError, ValueError, AttributeError):
        named = None
    names = ["can.log", "can.blf", "can.asc", "can.trc", "can.csv", "can.mf4"]
    if isinstance(named, str) and named and Path(named).name == named:
        names.insert(0, named)
    for name in names:
        if (run / name).is_file():
            return run / name
    raise HilError(f"{run}: no CAN log (the one summary.json names, can.log, ...) in this folder")


def marker_residuals(
    cycles: list[Cycle], kappa: np.ndarray, config: ArmConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What estimation.png marks: per cycle and segment whether a marker at either end of the
    segment was missing from a picture, shape (cycles, N); and for every marker seen, the time of
    its cycle [s] and its distance from where the estimate kappa (cycles, N) puts it [mm]."""
    missing = np.zeros((len(cycles), config.segments), dtype=bool)
    residual_t: list[float] = []
    residual: list[float] = []
    for c, (time_c, _, frames) in enumerate(cycles):
        if not frames:
            continue
        predicted = kinematics.markers(kappa[c], config.lengths, config.base)
        for frame in frames:
            seen = frame.seen
            missing[c] |= ~(seen[:-1] & seen[1:])
            distance = np.linalg.norm(frame.points[seen] - predicted[seen], axis=1)
            residual_t.extend([time_c] * len(distance))
            residual.extend((1e3 * distance).tolist())
    return missing, np.array(residual_t), np.array(residual)


def _plot(
    run: Path,
    config: ArmConfig,
    signals: dict[str, np.ndarray],
    cycles: list[Cycle],
    scores: dict[str, EstimatorScore],
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hil.plots import stack_layout

    t = signals["time"]
    n = config.segments
    chosen = scores[config.estimator]
    missing, residual_t, residual = marker_residuals(cycles, chosen.kappa, config)
    raw = scores["raw"].kappa
    fig, axes = plt.subplots(n + 1, 1, figsize=(9, 2.6 * (n + 1) + 0.6), sharex=True)
    for i in range(n):
        ax = axes[i]
        ax.plot(t, signals[f"kappa_{i + 1}"], color="black", lw=1.2, label="true")
        ax.plot(t, raw[:, i], color="tab:grey", lw=0.6, alpha=0.7, label="measured (raw)")
        for name, color in (("kf", "tab:green"), ("ukf", "tab:orange")):
            ax.plot(t, scores[name].kappa[:, i], color=color, lw=0.9, label=name)
        drops = missing[:, i]
        ax.plot(t[drops], raw[drops, i], "x", color="tab:red", ms=4, label="markers missing")
        gated = chosen.gated > 0
        ax.plot(
            t[gated],
            chosen.kappa[gated, i],
            "o",
            mfc="none",
            color="tab:purple",
            ms=5,
            label=f"outlier rejected ({config.estimator})",
        )
        ax.set_ylabel(f"segment {i + 1}\ncurvature [1/m]")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=7, ncol=3)
    axes[-1].plot(residual_t, residual, ".", ms=2, color="tab:blue")
    axes[-1].set_ylabel(f"marker residual\nvs {config.estimator} [mm]")
    axes[-1].set_xlabel("time [s]")
    axes[-1].grid(True, alpha=0.3)
    stack_layout(fig)
    path = run / "estimation.png"
    try:
        fig.savefig(path, dpi=100)
    except OSError as exc:
        raise HilError(f"{path}: cannot write: {exc.strerror or exc}") from None
    finally:
        plt.close(fig)
