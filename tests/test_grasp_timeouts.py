"""Settling phases that the grasp controller ended at `max_time`, not on their condition (the arm,
or the carried object, on target and at rest), are counted and listed in summary.json
(`settle_timeouts`, `settle_timeout_phases`) and the first is named in a warning; they passed
silently as a success (seed 1: the approach's and the carry's settling both ran 6.0 s)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil.run import RunOptions, run_scenario
from hil.scenario import load_scenario, resolve_scenario
from robots.planar_arm.controller.tasks import PHASE
from robots.planar_arm.plant.tasks import settle_timeouts

PERIOD = 0.01


def recording(stretches: list[tuple[int, str, float]]) -> tuple[np.ndarray, ...]:
    """Rows every PERIOD of (leg, phase name, seconds) stretches, in order."""
    legs, phases = [], []
    for leg, name, seconds in stretches:
        rows = round(seconds / PERIOD)
        legs += [leg] * rows
        phases += [PHASE[name]] * rows
    t = PERIOD * np.arange(len(legs))
    return t, np.array(legs, float), np.array(phases, float)


def test_a_settling_phase_that_lasted_max_time_is_a_timeout() -> None:
    t, leg, phase = recording(
        [
            (0, "moving", 1.0),
            (0, "settling", 6.0),  # timed out
            (0, "grasping", 1.0),
            (1, "moving", 2.0),
            (1, "settling", 5.9),  # settled a control period before max_time
            (1, "releasing", 1.0),
            (2, "settling", 6.0),  # timed out, straight after another leg's phase
            (2, "done", 0.5),
        ]
    )
    found = settle_timeouts(t, leg, phase, 6.0, PERIOD)
    assert found == [
        {"leg": "approach", "start": pytest.approx(1.0), "end": pytest.approx(7.0)},
        {"leg": "retreat", "start": pytest.approx(16.9), "end": pytest.approx(22.9)},
    ]


def test_a_settling_phase_cut_by_the_end_of_the_run_is_not_a_timeout() -> None:
    t, leg, phase = recording([(0, "moving", 1.0), (0, "settling", 8.0)])
    assert settle_timeouts(t, leg, phase, 6.0, PERIOD) == []


def test_a_run_whose_approach_settling_times_out_says_so(tmp_path: Path) -> None:
    """planar-grasp seed 1 with max_time 0.5 s: the approach settles from 1.45 s (the estimated
    tip is ~10 mm off then), so its settling ends at 1.95 s by max_time."""
    text = resolve_scenario("planar-grasp").read_text()
    text = text.replace("duration = 30.0", "duration = 2.2").replace(
        "max_time = 6.0", "max_time = 0.5"
    )
    path = tmp_path / "s.toml"
    path.write_text(text)
    summary = run_scenario(
        load_scenario(path), RunOptions(out=tmp_path / "run", inprocess=True, progress=False)
    ).summary
    assert summary["settle_timeouts"] == 1
    (first,) = summary["settle_timeout_phases"]
    assert first["leg"] == "approach"
    assert first["end"] - first["start"] == pytest.approx(0.5, abs=PERIOD)
    warning = (
        "1 settling phase(s) ended at max_time (0.5 s), not on target and at rest; first: the "
        f"approach leg's, {first['start']:.2f}-{first['end']:.2f} s"
    )
    assert warning in summary["warnings"]
