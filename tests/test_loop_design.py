"""Tests for controllers.loop_design and `hil tune`: the designed loop meets its phase margin at
a unit-gain crossover, a later estimate forces a slower loop, and the Bode plot is written where
asked (a PNG file; anything else is one line naming the path)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from controllers.curvature import SegmentModel
from controllers.loop_design import (
    design_outer_loop,
    effective_delay,
    estimator_delay,
    loop_transfer,
    write_bode_png,
)

T = 0.01  # [s]


@pytest.mark.parametrize("name", ["raw", "kf", "ukf"])
def test_design_meets_the_phase_margin_at_a_unit_gain_crossover(name: str) -> None:
    model = SegmentModel()
    delay = effective_delay(estimator_delay(name, T), T)
    design = design_outer_loop(model, delay, phase_margin_deg=60.0, max_crossover_hz=20.0)
    assert design.phase_margin_deg == pytest.approx(60.0, abs=0.5)
    loop = loop_transfer(model, design.gains, delay)
    wc = 2.0 * math.pi * design.crossover_hz
    assert abs(loop(1j * wc)) == pytest.approx(1.0, rel=1e-6)
    # the exact delay gives the same phase as the Pade approximant at the crossover
    assert math.degrees(np.angle(loop(1j * wc))) == pytest.approx(-120.0, abs=0.5)
    assert design.gain_margin > 2.0


def test_a_late_estimate_forces_a_slower_loop() -> None:
    model = SegmentModel()
    raw = design_outer_loop(model, effective_delay(estimator_delay("raw", T), T), 60.0, 20.0)
    kf = design_outer_loop(model, effective_delay(estimator_delay("kf", T), T), 60.0, 20.0)
    off = estimator_delay("kf", T, latency_compensation=False)
    assert off == estimator_delay("raw", T) > estimator_delay("ukf", T)
    assert raw.crossover_hz < kf.crossover_hz
    assert raw.gains.Kp < kf.gains.Kp


def test_the_crossover_cap_holds_and_leaves_more_margin() -> None:
    design = design_outer_loop(SegmentModel(), 0.015, 60.0, max_crossover_hz=2.0)
    assert design.crossover_hz == pytest.approx(2.0, rel=1e-6)
    assert design.phase_margin_deg == pytest.approx(90.0 - 360.0 * 2.0 * 0.015, abs=0.5)


def test_bad_inputs_name_the_problem() -> None:
    with pytest.raises(ValueError, match="unknown estimator 'pf'"):
        estimator_delay("pf", T)
    with pytest.raises(ValueError, match="phase_margin_deg"):
        design_outer_loop(SegmentModel(), 0.015, phase_margin_deg=95.0)


def test_bode_png_is_written(tmp_path: Path) -> None:
    design = design_outer_loop(SegmentModel(), 0.025)
    path = tmp_path / "bode.png"
    write_bode_png(SegmentModel(), design, path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _tune(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, list[str]]:
    from hil.cli import main

    code = main(["tune", *argv])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    return code, captured.out, captured.err.splitlines()


def test_hil_tune_of_a_fish_scenario_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from hil.scenario import resolve_scenario

    code, _, lines = _tune(capsys, str(resolve_scenario("fish-escape")))
    assert code == 1 and len(lines) == 1
    assert "hil tune applies to planar-arm scenarios" in lines[0] and "'fish'" in lines[0]


def test_hil_tune_out_is_a_png_file_and_its_path_is_printed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "afile").write_text("")
    (tmp_path / "folder").mkdir()
    for out, reason in (
        ("x.txt", "a PNG"),
        ("afile/x.png", "not a folder"),
        ("missing/x.png", "no such folder"),
        ("folder", "is a folder"),
        ("newdir/", "names a folder (it ends in /)"),  # wrote newdir.png before
    ):
        code, _, lines = _tune(capsys, "--out", str(tmp_path / out) + ("/" * out.endswith("/")))
        assert code == 1 and len(lines) == 1, out
        assert f"--out {tmp_path / out.rstrip('/')}" in lines[0] and reason in lines[0], lines
    assert not (tmp_path / "newdir.png").exists()
    code, _, lines = _tune(capsys, "--out", "")
    assert code == 1 and lines == ["hil: error: --out: an empty file name; name the PNG file"]
    code, printed, _ = _tune(capsys, "--out", str(tmp_path / "bode"))
    assert code == 0 and (tmp_path / "bode.png").read_bytes()[:4] == b"\x89PNG"
    assert printed.splitlines()[-1].endswith(f": {tmp_path / 'bode.png'}")
