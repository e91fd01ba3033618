"""The soft fish's task metrics (summary.json), from the true recorded signals.

Escape turn (stage 1 of a C-start, as FishBody/model.c defines it): from the onset of the head's
rotation (yaw rate beyond 1 % of its peak in the first manoeuvre) until the yaw rate first
returns to zero; `heading_change` [deg] is the yaw change from the manoeuvre's start to that end,
`turn_time` [s] its duration, `peak_yaw_rate` [deg/s] and `peak_acceleration` [m/s^2] (the head's
centroid) the largest over the manoeuvre. A manoeuvre starts when a valve driver opens its valve
and lasts until the next one starts (or the run ends). Its work split (the thesis's "Elastic and
Resistive Components of Work") is taken when the gas work over it peaks (the gas has done its
work; after that the channel vents): gas work, elastic energy stored, kinetic energy and energy
dissipated since the manoeuvre's start, so elastic + kinetic + resistive = gas work there.
Invariant: only true signals are scored; the controller's reports are only quoted.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from hil.scenario import Scenario
    from robots.fish.plant.rig import Fish

HOLD_MODE = 4  # FishState.mode "hold"
NO_GAS_MODE = 6


def manoeuvre_starts(signals: Mapping[str, np.ndarray]) -> list[tuple[int, int]]:
    """(sample index, valve) of every valve opening, in time order."""
    starts = []
    for n in (1, 2):
        opened = np.nan_to_num(signals[f"open_{n}"]) > 0.5
        rises = np.flatnonzero(opened[1:] & ~opened[:-1]) + 1
        if opened.size and opened[0]:
            rises = np.concatenate([[0], rises])
        starts += [(int(k), n) for k in rises]
    return sorted(starts)


def stage_one(signals: Mapping[str, np.ndarray], begin: int, end: int) -> dict[str, Any]:
    """Heading change, turn time, peak yaw rate and acceleration of the turn in [begin, end)."""
    t, yaw, rate = signals["time"], signals["yaw"], signals["yaw_rate"]
    window = slice(begin, end)
    rates = rate[window]
    peak = float(np.abs(rates).max()) if rates.size else 0.0
    out: dict[str, Any] = {
        "peak_yaw_rate": math.degrees(peak),
        "peak_acceleration": float(np.max(signals["a_head"][window])) if rates.size else 0.0,
        "heading_change": None,
        "turn_time": None,
    }
    if peak == 0.0:
        return out
    onset = begin + int(np.argmax(np.abs(rates) > 0.01 * peak))
    turn = math.copysign(1.0, rate[onset])
    after = turn * rate[onset:end] <= 0.0
    if not after.any():
        return out  # stage 1 does not end within the manoeuvre
    stop = onset + int(np.argmax(after))
    out["heading_change"] = math.degrees(turn * (yaw[stop] - yaw[begin]))
    out["turn_time"] = float(t[stop] - t[onset])
    out["direction"] = "left" if turn > 0 else "right"
    return out


def work_split(signals: Mapping[str, np.ndarray], begin: int, end: int) -> dict[str, float]:
    """The manoeuvre's work split at its peak gas work (module docstring) [J]."""
    gas = signals["W_gas"][begin:end] - signals["W_gas"][begin]
    k = begin + int(np.argmax(gas))
    split = {
        name: float(signals[column][k] - signals[column][begin])
        for name, column in (
            ("gas_work", "W_gas"),
            ("elastic", "E_elastic"),
            ("kinetic", "E_kinetic"),
            ("resistive", "E_resistive"),
        )
    }
    split["at"] = float(signals["time"][k])
    total = split["gas_work"]
    split["elastic_share"] = split["elastic"] / total if total > 0 else math.nan
    split["resistive_share"] = split["resistive"] / total if total > 0 else math.nan
    return split


def beat_mean(values: np.ndarray, window: int) -> np.ndarray:
    """A centred moving mean over `window` samples (shorter at the ends)."""
    window = max(1, window)
    kernel = np.ones(window)
    sums = np.convolve(values, kernel, mode="same")
    counts = np.convolve(np.ones_like(values), kernel, mode="same")
    return sums / counts


def fish_metrics(robot: Fish, scenario: Scenario, signals: Mapping[str, Any]) -> dict[str, Any]:
    """The fish's metrics for summary.json (module docstring): the first manoeuvre's turn, the
    work split of every manoeuvre, the swimming speed, the gas, the task's score and why the
    run ended; `task_warnings` for summary.json's warnings."""
    t = signals["time"]
    starts = manoeuvre_starts(signals)
    length = robot.body_length(scenario)
    bounds = [k for k, _ in starts] + [t.size]
    manoeuvres = []
    for i, (k, valve) in enumerate(starts):
        entry: dict[str, Any] = {"start": float(t[k]), "valve": valve}
        entry.update(work_split(signals, k, bounds[i + 1]))
        manoeuvres.append(entry)
    first = stage_one(signals, starts[0][0], bounds[1]) if starts else {}
    begin = starts[0][0] if starts else 0
    surge = signals["surge"][begin:]
    forward = float(np.mean(surge)) if surge.size else 0.0
    reported = signals["manoeuvres_left"][np.isfinite(signals["manoeuvres_left"])]
    gas_used = float(signals["m_canister"][0] - signals["m_canister"][-1])
    metrics: dict[str, Any] = {
        "heading_change": first.get("heading_change"),  # its size; the turn's way:
        "turn_direction": first.get("direction"),  # "left" (yaw up) or "right"
        "turn_time": first.get("turn_time"),
        "peak_yaw_rate": first.get("peak_yaw_rate"),
        "peak_acceleration": first.get("peak_acceleration"),
        "forward_speed": forward,
        "forward_speed_bl": forward / length,
        "body_length": length,
        "final_heading": math.degrees(float(signals["yaw"][-1])),
        "gas_used": gas_used,
        "manoeuvres": len(starts),
        "manoeuvres_left": _manoeuvres_left(robot, scenario, signals, len(starts), gas_used),
        "manoeuvres_left_reported": int(reported[-1]) if reported.size else None,
        "work": manoeuvres,
        "work_violations": sum(
            1 for m in manoeuvres if m["elastic"] + m["resistive"] > m["gas_work"] + 1e-9
        ),
    }
    seen = robot.camera_view(scenario)
    gone = np.abs(np.c_[signals["nose_x"], signals["nose_y"]]).max(axis=1) > seen
    metrics["nose_out_of_view_at"] = float(t[int(np.argmax(gone))]) if gone.any() else None
    warnings: list[str] = []
    kind = scenario.task.kind
    if kind == "escape":
        success = metrics["heading_change"] is not None and len(starts) >= 1
    elif kind == "swim":
        success = forward > 0.0
    else:
        success = _heading_held(scenario, signals, metrics, warnings)
    success = _end_reason(scenario, signals, metrics) and success
    metrics["success"] = bool(success)
    metrics["task_warnings"] = warnings  # summary.json's warnings, not a metric of its own
    return metrics


def _manoeuvres_left(
    robot: Fish, scenario: Scenario, signals: Mapping[str, Any], starts: int, gas_used: float
) -> int | None:
    """How many more manoeuvres the gas left above the controller's reserve allows, at the
    mean gas of the `starts` made; None if none was made (or no gas used). The true figure:
    the controller's report saturates at 255 (an 8-bit signal)."""
    if not (starts and gas_used > 0.0):
        return None
    usable = float(signals["m_canister"][-1]) - robot.controller_config(scenario).gas_reserve
    return max(0, math.floor(usable / (gas_used / starts)))


def _heading_held(
    scenario: Scenario, signals: Mapping[str, Any], metrics: dict[str, Any], warnings: list[str]
) -> bool:
    """The heading task: whether the beat-averaged heading stayed within the controller's
    tolerance of the set heading from the hold's start on; its start and errors into
    `metrics`, and a warning into `warnings` if the nose left the camera's view before it."""
    t, r = signals["time"], scenario.robot
    holding = np.flatnonzero(np.nan_to_num(signals["mode"]) == HOLD_MODE)
    window = round(1.0 / (r.frequency * scenario.timing.control_period))
    mean_yaw = beat_mean(signals["yaw"], window)
    target = math.radians(r.heading)
    errors = np.degrees(np.abs((mean_yaw - target + math.pi) % (2 * math.pi) - math.pi))
    if not holding.size:
        metrics["hold_start"] = metrics["heading_error_max"] = None
        metrics["heading_error_mean"] = None
        return False
    # after the first turn, once the head has come to rest and the fish swims on; the
    # last half beat is left out (the centred mean is one-sided there)
    held = errors[holding[0] : max(holding[0] + 1, t.size - window // 2)]
    metrics["hold_start"] = float(t[holding[0]])
    metrics["heading_error_max"] = float(held.max())
    metrics["heading_error_mean"] = float(held.mean())
    left = metrics["nose_out_of_view_at"]
    if left is not None and left < metrics["hold_start"]:
        warnings.append(
            f"the nose left the camera's view at t = {left:.3f} s, before the hold "
            f"({metrics['hold_start']:.3f} s): the controller glided without a "
            "heading estimate; the heading is scored from the true signals"
        )
    return bool(held.max() <= math.degrees(scenario_tolerance()))


def _end_reason(scenario: Scenario, signals: Mapping[str, Any], metrics: dict[str, Any]) -> bool:
    """Why the run ended, into `metrics` (`end_reason`, `gas_exhausted`): the canister ran
    down (saying whether the controller reported it), or the task ran its duration. False if
    the gas ran out (no task succeeds then)."""
    t = signals["time"]
    empty = np.nan_to_num(signals["empty"]) > 0.5
    if not empty.any():
        metrics["end_reason"] = f"the {scenario.task.kind} task ran its {scenario.duration:g} s"
        metrics["gas_exhausted"] = False
        return True
    reported_no_gas = np.nan_to_num(signals["mode"]) == NO_GAS_MODE
    k = int(np.argmax(empty))
    told = f"t = {t[int(np.argmax(reported_no_gas))]:.3f} s" if reported_no_gas.any() else None
    metrics["end_reason"] = (
        f"the canister ran down at t = {t[k]:.3f} s (supply below the set pressure); "
        + (
            f"the controller reported no gas at {told} and stopped manoeuvring"
            if told
            else "the controller did not report it"
        )
    )
    metrics["gas_exhausted"] = True
    return False


def scenario_tolerance() -> float:
    """The heading task's tolerance [rad]: the controller's (robots.fish.controller.FishConfig)."""
    from robots.fish.controller import FishConfig

    return FishConfig.tolerance  # the field's default
