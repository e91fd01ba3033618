"""ruff (lint and format) and mypy over the checkout as part of the test run, at the versions the
`test` extra pins; and the complexity report (`tests/complexity.py`) on files made to measure.

Each tool runs as `python -m TOOL` from the project root, from the environment running the tests
(the one `pip install -e '.[test]'` filled), with the project's own configuration
(pyproject.toml). A tool at another version than its pin fails by name, before it runs: a newer
ruff or mypy finds new things to say, and that is an upgrade to make on purpose, not a surprise.
The tools write only their caches into the checkout (.ruff_cache, .mypy_cache).
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import pytest

from tests.complexity import Complex, Long, format_report, report

ROOT = Path(__file__).resolve().parents[1]
PINNED = ("ruff", "mypy", "radon")
CHECKS = {
    "ruff-check": ("ruff", "check", "."),
    "ruff-format": ("ruff", "format", "--check", "."),
    "mypy": ("mypy",),  # the packages pyproject.toml's [tool.mypy] names
}
TIMEOUT = 900  # [s] a guard against a hung tool, not a speed target (mypy: about 35 s cold)


def pinned_versions() -> dict[str, str]:
    """The exact versions (`name==X`) pinned in pyproject.toml's `test` extra, by name."""
    with open(ROOT / "pyproject.toml", "rb") as file:
        extra = tomllib.load(file)["project"]["optional-dependencies"]["test"]
    pins = {}
    for requirement in extra:
        name, exact, pinned = requirement.partition("==")
        if exact:
            pins[name.strip().lower()] = pinned.strip()
    return pins


def require_pinned(tool: str) -> None:
    """Fail, naming `tool`, unless it is pinned exactly and installed at its pin."""
    pinned = pinned_versions().get(tool)
    assert pinned is not None, f"pyproject.toml's test extra pins no exact version of {tool}"
    try:
        installed = version(tool)
    except PackageNotFoundError:
        pytest.fail(f"{tool} is not installed: pip install -e '.[test]' ({tool}=={pinned})")
    assert installed == pinned, (
        f"{tool} {installed} is installed, the test extra pins {tool}=={pinned}: "
        "pip install -e '.[test]' (or move the pin on purpose, and fix what the new one finds)"
    )


@pytest.mark.parametrize("tool", PINNED)
def test_each_tool_is_pinned_and_installed_at_its_pin(tool: str) -> None:
    require_pinned(tool)


def test_a_tool_at_another_version_or_missing_fails_by_name(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    pinned = pinned_versions()["mypy"]
    module = sys.modules[__name__]
    monkeypatch.setattr(module, "version", lambda name: "0.0.1")
    with pytest.raises(AssertionError, match=rf"^mypy 0\.0\.1 is installed, .* mypy=={pinned}:"):
        require_pinned("mypy")

    def missing(name: str) -> str:
        raise PackageNotFoundError(name)

    monkeypatch.setattr(module, "version", missing)
    with pytest.raises(
        pytest.fail.Exception,
        match=rf"^radon is not installed: .*radon=={pinned_versions()['radon']}\)$",
    ):
        require_pinned("radon")
    with pytest.raises(AssertionError, match="pins no exact version of pytest"):
        require_pinned("pytest")  # pytest>=8: not pinned


@pytest.mark.parametrize("check", CHECKS)
def test_the_checkout_is_clean(check: str) -> None:
    command = CHECKS[check]
    require_pinned(command[0])
    result = subprocess.run(
        [sys.executable, "-m", *command],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
    )
    assert result.returncode == 0, (
        f"`{' '.join(command)}` exited {result.returncode}:\n{result.stdout}{result.stderr}"
    )


def branches(name: str, complexity: int, indent: str = "") -> str:
    """A function `name` of cyclomatic complexity `complexity` (one `if` a point above 1)."""
    body = "".join(
        f"{indent}    if x == {i}:\n{indent}        return {i}\n" for i in range(complexity - 1)
    )
    return f"{indent}def {name}(x):\n{body}{indent}    return -1\n"


def write_lines(path: Path, text: str, lines: int) -> Path:
    """`text` padded with comment lines to `lines` lines in all."""
    count = text.count("\n")
    assert count <= lines
    path.write_text(text + "# padding\n" * (lines - count))
    return path


def line_of(source: str, definition: str) -> int:
    """The line (from 1) where `definition` ("def NAME") is in `source`."""
    return source[: source.index(definition)].count("\n") + 1


def test_the_complexity_report_lists_what_exceeds_the_limits(tmp_path: Path) -> None:
    closure = "def outer(x):\n" + branches("inner", 21, "    ") + "    return inner(x)\n"
    method = "class Arm:\n" + branches("step", 22, "    ")
    source = branches("at_limit", 20) + branches("above", 21) + closure + method
    write_lines(tmp_path / "long.py", source, 601)
    (tmp_path / "package" / "__pycache__").mkdir(parents=True)
    write_lines(tmp_path / "package" / "at_limit.py", branches("short", 3), 600)
    write_lines(tmp_path / "package" / "__pycache__" / "stale.py", branches("stale", 30), 700)

    functions, modules = report([tmp_path], tmp_path)

    assert functions == [
        Complex("long.py", line_of(source, "    def step"), "Arm.step", 22),
        Complex("long.py", line_of(source, "def above"), "above", 21),
        Complex("long.py", line_of(source, "    def inner"), "outer.inner", 21),
    ]
    assert modules == [Long("long.py", 601)]
    text = format_report(functions, modules)
    assert text.splitlines()[0] == "functions above cyclomatic complexity 20: 3"
    assert f"    22  long.py:{line_of(source, '    def step')}  Arm.step" in text.splitlines()
    assert text.splitlines()[-2:] == ["modules above 600 lines: 1", "   601  long.py"]


def test_the_complexity_report_takes_its_limits_and_single_files(tmp_path: Path) -> None:
    path = write_lines(tmp_path / "short.py", branches("small", 3), 10)
    assert report([path], tmp_path, max_complexity=2, max_lines=9) == (
        [Complex("short.py", 1, "small", 3)],
        [Long("short.py", 10)],
    )
    assert report([path], tmp_path, max_complexity=3, max_lines=10) == ([], [])
