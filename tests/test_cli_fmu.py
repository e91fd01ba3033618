"""The `hil` CLI as a user runs it: help with examples, fmu build/list/check, one-line errors."""

from __future__ import annotations

import subprocess
import sys

import pytest

from hil.cli import build_parser, main


def run_hil(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "hil", *args], capture_output=True, text=True, timeout=120
    )


def test_every_help_shows_an_example() -> None:
    parser = build_parser()
    assert "examples:" in parser.format_help()
    subparsers = [a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"]
    pending = list(subparsers[0].choices.items())
    assert {"run", "fmu"} <= {name for name, _ in pending}
    while pending:
        name, sub = pending.pop()
        assert "examples:" in sub.format_help(), name
        for action in sub._actions:
            if action.__class__.__name__ == "_SubParsersAction":
                pending += [(f"{name} {n}", p) for n, p in action.choices.items()]


def test_fmu_check_passes_for_both_models() -> None:
    for name in ("DriveCylinder", "FeaSegment"):
        result = run_hil("fmu", "check", name)
        assert result.returncode == 0, result.stderr
        assert f"{name}: fmpy validation passed" in result.stdout
    # every output with its unit, as the modelDescription declares it
    lines = result.stdout.splitlines()
    assert any(line.startswith("  p_a = ") and line.endswith(" Pa") for line in lines)
    assert any(line.startswith("  kappa = ") and line.endswith(" 1/m") for line in lines)


def test_fmu_check_unknown_model_is_one_line_error() -> None:
    result = run_hil("fmu", "check", "Nope")
    assert result.returncode == 1
    assert result.stderr.strip().count("\n") == 0
    assert "unknown FMU model 'Nope'" in result.stderr


def test_fmu_check_rejects_a_broken_fmu_file(tmp_path) -> None:
    broken = tmp_path / "Broken.fmu"
    broken.write_bytes(b"not a zip")
    assert main(["fmu", "check", str(broken)]) == 1


def test_fmu_list_shows_variables_with_units(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fmu", "list"]) == 0
    out = capsys.readouterr().out
    assert "DriveCylinder:" in out and "FeaSegment:" in out
    assert any(line.split()[:4] == ["x_ref", "input", "Real", "m"] for line in out.splitlines())
    assert any(line.split()[:4] == ["p_a", "output", "Real", "Pa"] for line in out.splitlines())


def test_fmu_build_prints_paths(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fmu", "build", "FeaSegment"]) == 0
    assert capsys.readouterr().out.startswith("FeaSegment: ")
