"""`hil fmu check` refuses a stop time or step that would hang it, in one line, before building."""

from __future__ import annotations

import pytest

from hil.cli import fmu as fmu_cli
from hil.cli import main


@pytest.fixture(autouse=True)
def _no_build(monkeypatch: pytest.MonkeyPatch) -> None:
    """The limits are checked before anything is built or simulated."""

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("build_fmu called although the arguments were refused")

    monkeypatch.setattr(fmu_cli, "build_fmu", refuse)


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--stop-time", "1e6"], "--stop-time must be in (0, 100] s for a check, got 1e+06"),
        (["--stop-time", "100.001"], "--stop-time must be in (0, 100] s"),
        (["--stop-time", "inf"], "--stop-time must be in (0, 100] s"),
        (["--stop-time", "nan"], "--stop-time must be in (0, 100] s"),
        (["--stop-time", "0"], "--stop-time must be in (0, 100] s"),
        (["--stop-time", "-1"], "--stop-time must be in (0, 100] s"),
        (["--step", "0"], "--step must be in (0, --stop-time 0.5] s, got 0"),
        (["--step", "-0.001"], "--step must be in (0, --stop-time 0.5] s"),
        (["--step", "nan"], "--step must be in (0, --stop-time 0.5] s"),
        (["--step", "1"], "--step must be in (0, --stop-time 0.5] s, got 1"),
        (["--step", "1e-300"], "--step 1e-300 s would take 5e+299 steps"),
        (["--stop-time", "100", "--step", "0.0009"], "--step 0.0009 s would take 1.11e+05 steps"),
    ],
)
def test_refused_in_one_line(
    args: list[str], expected: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["fmu", "check", "DriveCylinder", *args]) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith(f"hil: error: {expected}")
    assert err.count("\n") == 1


def test_limits_at_the_edge_are_accepted() -> None:
    fmu_cli._check_limits(fmu_cli.MAX_CHECK_STOP_TIME, None)
    fmu_cli._check_limits(100.0, 100.0 / fmu_cli.MAX_CHECK_STEPS)
    fmu_cli._check_limits(0.5, 0.5)


def test_step_is_used(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    from hil.fmu.build import build_fmu

    monkeypatch.setattr(fmu_cli, "build_fmu", build_fmu)
    assert main(["fmu", "check", "FeaSegment", "--stop-time", "0.1", "--step", "0.01"]) == 0
    out = capsys.readouterr().out
    # 11 samples (t = 0, 0.01, ..., 0.1) plus the input step at 0.05 s recorded twice.
    samples = int(out.split(" samples")[0].rsplit(" ", 1)[1])
    assert 11 <= samples <= 13
