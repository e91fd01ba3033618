"""Task metrics of a run (`summary.json`): tracking error, overshoot, settling, bus load, frames.

Metrics are computed from the recorded signals against the plant's own evaluation of the
reference profile (the same function the controller tracks). Step metrics use every step hold
of the profile: overshoot as a fraction of the step, settling time into a +-5 % band of the step
(measured from the step), steady-state error as the mean |error| over the last 20 % of the hold.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from hil.errors import HilError
from hil.plant import PlantStats
from hil.recording import CanLogger
from hil.rig import robot_kind
from hil.scenario import Scenario
from rigbus.protocol import Protocol, bus_load

SETTLING_BAND = 0.05
BUS_LOAD_WARNING = 0.70


def read_signals(path: Path) -> dict[str, np.ndarray]:
    """The signals CSV as columns (empty cells are NaN). HilError naming the file if it is
    missing, unreadable or empty, and the line if one is cut short (fewer cells than the header,
    or a last line without its line end: softhil writes whole lines) or holds a cell that is not
    a number."""
    try:
        with path.open(newline="", encoding="utf-8") as f:
            text = f.read()
    except FileNotFoundError:
        blocks = path.with_suffix(".parquet")
        hint = (
            f" (its blocks are in {blocks.name}: hil csv {path.parent})" if blocks.is_dir() else ""
        )
        raise HilError(f"{path}: no such file{hint}") from None
    except IsADirectoryError:
        raise HilError(f"{path}: is a folder, not a signals CSV") from None
    except OSError as exc:
        raise HilError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise HilError(f"{path}: not a signals CSV (not UTF-8 text)") from None
    try:
        rows = list(csv.reader(io.StringIO(text, newline="")))
    except csv.Error as exc:
        raise HilError(f"{path}: not a signals CSV ({exc})") from None
    if not rows or not rows[0]:
        raise HilError(f"{path}: empty: no header line of signal names")
    header, body = rows[0], rows[1:]
    for line, row in enumerate(body, start=2):
        if len(row) != len(header):
            cut = " (a file cut short?)" if len(row) < len(header) else ""
            raise HilError(
                f"{path}: line {line}: {len(row)} cells where the header names {len(header)}{cut}"
            )
    if not text.endswith(("\n", "\r")):
        raise HilError(f"{path}: line {len(rows)}: cut short (the last line has no line end)")
    columns: dict[str, np.ndarray] = {}
    for i, name in enumerate(header):
        try:
            columns[name] = np.array([float(r[i]) if r[i] else math.nan for r in body])
        except ValueError:
            line, cell = next((n, r[i]) for n, r in enumerate(body, start=2) if not _number(r[i]))
            raise HilError(
                f"{path}: line {line}, column {name}: {cell!r} is not a number"
            ) from None
    return columns


def _number(cell: str) -> bool:
    try:
        float(cell or "nan")
    except ValueError:
        return False
    return True


def bus_load_of(scenario: Scenario, protocol: Protocol) -> float:
    """Bus load implied by the robot's frames at the scenario's rates, from the DBC's frame
    lengths, at its bitrate."""
    rates = robot_kind(scenario.robot.kind).frame_rates(scenario, protocol)
    return bus_load(rates, scenario.bus.bitrate, protocol)


def step_metrics(
    t: np.ndarray, kappa: np.ndarray, holds: list[tuple[float, float, float]], initial: float = 0.0
) -> list[dict[str, float]]:
    """Overshoot, settling time and steady-state error of each step hold."""
    results = []
    previous = initial
    for start, end, level in holds:
        step = level - previous
        previous = level
        if abs(step) < 1e-12:
            continue
        window = (t >= start) & (t < end)
        tw, kw = t[window], kappa[window]
        if tw.size < 2:
            continue
        overshoot = max(0.0, float(np.max(np.sign(step) * (kw - level))) / abs(step))
        outside = np.nonzero(np.abs(kw - level) > SETTLING_BAND * abs(step))[0]
        if outside.size == 0:
            settling = 0.0
        elif outside[-1] + 1 < tw.size:
            settling = float(tw[outside[-1] + 1] - start)
        else:
            settling = math.inf
        tail = tw >= end - 0.2 * (end - start)
        if not np.any(tail):
            tail[-1] = True
        steady = float(np.mean(np.abs(kw[tail] - level)))
        results.append(
            {
                "start": start,
                "level": level,
                "step": step,
                "overshoot": overshoot,
                "settling_time": settling,
                "steady_state_error": steady,
            }
        )
    return results


def curvature_metrics(scenario: Scenario, signals: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """The curvature-profile task's metrics: RMS tracking error against the reference the
    controller reported, and per segment the step metrics of every hold and the sine's RMS."""
    t = signals["time"]
    n = scenario.robot.segments
    errors = np.concatenate(
        [signals[f"kappa_ref_{i}"] - signals[f"kappa_{i}"] for i in range(1, n + 1)]
    )
    errors = errors[np.isfinite(errors)]
    task = scenario.task
    profile = task.profile()
    segments: list[dict[str, Any]] = []
    all_steps: list[dict[str, float]] = []
    for i in range(1, n + 1):
        scale = task.scale[(i - 1) % len(task.scale)]
        holds = [(a, b, scale * level) for a, b, level in profile.step_times(scenario.duration)]
        steps = step_metrics(t, signals[f"kappa_{i}"], holds)
        sine = None
        if task.sine is not None:
            in_sine = t >= task.sine.start + 1.0 / task.sine.frequency  # after one period
            e = signals[f"kappa_ref_{i}"][in_sine] - signals[f"kappa_{i}"][in_sine]
            e = e[np.isfinite(e)]
            if e.size:
                sine = float(np.sqrt(np.mean(e**2)))
        segments.append({"segment": i, "steps": steps, "sine_rms_error": sine})
        all_steps += steps
    return {
        "rms_tracking_error": float(np.sqrt(np.mean(errors**2))) if errors.size else None,
        # None where the task has no step to measure (a sine-only or very short run)
        "max_overshoot": max((s["overshoot"] for s in all_steps), default=None),
        "settling_time": max((s["settling_time"] for s in all_steps), default=None),
        "steady_state_error": max((s["steady_state_error"] for s in all_steps), default=None),
        "segments": segments,
    }


def summarise(
    scenario: Scenario,
    signals_path: Path,
    stats: PlantStats,
    can_log: CanLogger,
    controller_report: dict[str, Any],
    protocol: Protocol,
) -> dict[str, Any]:
    signals = read_signals(signals_path)
    t = signals["time"]
    metrics = robot_kind(scenario.robot.kind).task_metrics(scenario, signals)
    task_warnings = metrics.pop("task_warnings", [])  # what the task's scoring found
    duration = float(t[-1] - t[0]) if t.size > 1 else 0.0
    load = bus_load_of(scenario, protocol)
    warnings = list(task_warnings)
    if load > BUS_LOAD_WARNING:
        warnings.append(f"bus load {100 * load:.0f} % exceeds {100 * BUS_LOAD_WARNING:.0f} %")
    if stats.emcy_sent:
        warnings.append(
            f"{stats.emcy_sent} EMCY frame(s): a drive held its piston "
            "(over-pressure or command timeout), see the CAN log"
        )
    if stats.setpoints_clamped:
        warnings.append(
            f"{stats.setpoints_clamped} SYNC(s) after a period whose drive setpoint lay outside "
            f"the stroke, clamped by the servo (DriveStatus fault bit 2); first: "
            f"{stats.first_clamped}"
        )
    missed = stats.commands_missed + int(controller_report.get("status_missed", 0))
    stale = stats.commands_stale + int(controller_report.get("stale_frames", 0))
    if missed or stale:
        warnings.append(
            f"{missed} missed and {stale} stale frame(s) held over (policy "
            f"{scenario.controller.policy})"
        )
    intrusions = intrusions_of(stats, controller_report)
    if intrusions["count"]:
        warnings.append(
            f"{intrusions['count']} frame(s) from a node that is not their sender (intrusions); "
            f"first: {intrusions['first']}"
        )
    notes = controller_report.get("notes", [])
    if isinstance(notes, list):  # a program's report may hold anything (hil.run checks it)
        warnings.extend(f"controller: {n}" for n in notes if isinstance(n, str))
    if metrics.get("settling_time") is not None and math.isinf(metrics["settling_time"]):
        warnings.append("a step never settled within its hold (settling_time is null)")
    return {
        "scenario": scenario.name,
        "seed": scenario.seed,
        "status": "completed",
        "duration": scenario.duration,
        **metrics,
        "real_time_factor": scenario.duration / stats.wall_time if stats.wall_time > 0 else None,
        "wall_time": stats.wall_time,  # the SYNC loop; the controller's start-up is apart
        "startup_time": stats.startup_time,
        "bus_load": load,
        "bus_load_measured": can_log.bits / scenario.bus.bitrate / duration if duration else None,
        "bitrate": scenario.bus.bitrate,
        "log_start": can_log.start,
        "can_log": can_log.path.name,
        "frames": {
            "sent": can_log.sent,
            "received": can_log.received,
            "missed": missed,
            "stale": stale,
            "unknown": stats.unknown_frames + int(controller_report.get("unknown_frames", 0)),
            "emcy": stats.emcy_sent,
        },
        "intrusions": intrusions,
        "controller": controller_report,
        "plant": asdict(stats),
        "warnings": warnings,
    }


def intrusions_of(stats: PlantStats, controller_report: Mapping[str, Any]) -> dict[str, Any]:
    """Frames that came from a node other than their one legitimate sender, as the plant and
    the controller each saw them: {"count": N, "first": "..."} (first: the plant's, if any)."""
    count = stats.intrusions + int(controller_report.get("intrusions", 0))
    first = stats.first_intrusion or str(controller_report.get("first_intrusion", ""))
    return {"count": count, "first": first or None}


def realtime_failure(scenario: Scenario, report: Mapping[str, Any]) -> str | None:
    """Why a real-time run failed its timing (None if it did not, or was not real-time): more
    than [controller] max_overruns (a fraction, 1 % by default) of its SYNCs over one control
    period late, or a SYNC later than [controller] max_lateness (default one period)."""
    if not report.get("realtime"):
        return None
    period = scenario.timing.control_period
    limit = scenario.controller.max_lateness or period
    syncs = int(report.get("cycles", 0)) + 1
    overruns = int(report.get("overruns", 0))
    late = float(report.get("max_lateness", 0.0))
    allowed = scenario.controller.max_overruns
    if overruns > allowed * syncs:
        return (
            f"real-time run failed: {overruns} of {syncs} SYNCs were more than one control period "
            f"({1e3 * period:g} ms) late (controller.max_overruns = {100 * allowed:g} %)"
        )
    if late > limit:
        return (
            f"real-time run failed: a SYNC was {1e3 * late:.2f} ms late, beyond "
            f"controller.max_lateness = {1e3 * limit:g} ms"
        )
    return None
