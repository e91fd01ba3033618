"""The house's limits, held: no function above radon cyclomatic complexity 20 and no module above
600 lines without a docstring sentence stating why, in hil, controllers, rigbus, robots and
fmus/*.py (tests/complexity.py measures; `python -m tests.complexity --check` is the same gate).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.complexity import (
    MAX_LINES,
    ROOT,
    Complex,
    Long,
    breaches,
    default_paths,
    format_report,
    main,
    report,
    stated_reason,
)
from tests.test_lint import branches, write_lines


def test_the_house_holds_its_limits() -> None:
    found = report(default_paths())
    assert breaches(*found) == [], format_report(*found)


def test_the_gate_reads_the_packages_and_the_fmus_modules_only() -> None:
    shown = {p.relative_to(ROOT).as_posix() for p in default_paths()}
    assert shown == {"hil", "controllers", "rigbus", "robots", "fmus/__init__.py"}


def test_a_function_above_20_breaks_the_limit_and_one_at_20_does_not(tmp_path: Path) -> None:
    path = tmp_path / "module.py"
    path.write_text(branches("at_limit", 20) + branches("above", 21))
    found = report([path], tmp_path)
    assert found == ([Complex("module.py", 41, "above", 21)], [])
    assert breaches(*found) == ["module.py:41 above: complexity 21"]
    path.write_text(branches("at_limit", 20))
    assert breaches(*report([path], tmp_path)) == []


def test_a_method_or_closure_above_20_breaks_the_limit(tmp_path: Path) -> None:
    closure = "def outer(x):\n" + branches("inner", 21, "    ") + "    return inner(x)\n"
    method = "class Arm:\n" + branches("step", 21, "    ")
    path = tmp_path / "module.py"
    path.write_text(closure + method)
    assert [b.split(" ")[1] for b in breaches(*report([path], tmp_path))] == [
        "outer.inner:",
        "Arm.step:",
    ]


STATED = "It stays above 600 lines: the DBC's messages are one table, read in one pass."


@pytest.mark.parametrize(
    ("docstring", "stated"),
    [
        (f"Tables.\n\n{STATED}\n", True),
        ("Tables. It is kept above 600 lines because its parts share one cache.", True),
        ("Tables.\n\nIt stays above 600\nlines (about 930): the kinds are one table.", True),
        ("Tables.", False),  # no word of it
        ("Tables. It is above 600 lines.", False),  # no reason
        ("Tables. It stays above 600 lines: one table.", False),  # two words are not a reason
        ("Tables. It stays above 600 lines: one shared table.", True),  # three are
        ("Tables. It stays above 500 lines: the DBC's messages are one table.", False),
        ("Tables. It stays above 6000 lines: the DBC's messages are one table.", False),
        ("It is long: above 600 lines.", False),  # the reason comes before, not after
    ],
)
def test_a_long_modules_reason_is_a_docstring_sentence(docstring: str, stated: bool) -> None:
    text = f'"""{docstring}"""\n\nVALUE = 1\n'
    assert bool(stated_reason(text)) is stated
    assert bool(stated_reason(text.replace('"""', "'''"))) is stated


def test_a_reason_outside_the_module_docstring_does_not_count() -> None:
    assert stated_reason(f"# {STATED}\nVALUE = 1\n") == ""
    assert stated_reason(f'VALUE = 1\n"""{STATED}"""\n') == ""
    assert stated_reason(f'def f():\n    """{STATED}"""\n') == ""
    assert stated_reason("def broken(:\n") == ""
    assert stated_reason(f'"""{STATED}"""\n', max_lines=700) == ""


def test_a_long_module_breaks_the_limit_unless_its_docstring_states_why(tmp_path: Path) -> None:
    silent = write_lines(tmp_path / "silent.py", '"""Tables."""\n', MAX_LINES + 1)
    stated = write_lines(tmp_path / "stated.py", f'"""Tables.\n\n{STATED}\n"""\n', MAX_LINES + 1)
    at_limit = write_lines(tmp_path / "at_limit.py", '"""Tables."""\n', MAX_LINES)
    found = report([tmp_path], tmp_path)
    assert found == ([], [Long("silent.py", 601), Long("stated.py", 601, STATED)])
    assert breaches(*found) == [
        "silent.py: 601 lines, no docstring sentence says why it is above the limit"
    ]
    assert format_report(*found).splitlines()[-2:] == [
        "   601  silent.py",
        "   601  stated.py  (reason stated)",
    ]
    assert breaches(*report([stated, at_limit], tmp_path)) == []
    assert report([silent], tmp_path, max_lines=MAX_LINES + 1) == ([], [])
    other = STATED.replace("600", "500")  # under another limit, the reason names that one
    write_lines(stated, f'"""Tables.\n\n{other}\n"""\n', MAX_LINES + 1)
    assert report([stated], tmp_path, max_lines=500) == ([], [Long("stated.py", 601, other)])
    assert breaches(*report([stated], tmp_path)) != []


def test_check_exits_1_on_a_breach_and_the_report_exits_0(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "module.py"
    path.write_text(branches("above", 21))
    assert main([str(path)]) == 0
    assert main(["--check", str(path)]) == 1
    assert "functions above cyclomatic complexity 20: 1" in capsys.readouterr().out
    assert main(["--check", "--max-complexity", "21", str(path)]) == 0
    path.write_text(branches("at_limit", 20))
    assert main(["--check", str(path)]) == 0
