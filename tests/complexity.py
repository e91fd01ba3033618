"""The complexity report: functions above a cyclomatic complexity and modules above a length,
measured by radon (pinned in the `test` extra), in the packages the house holds to them.

    python -m tests.complexity [--max-complexity 20] [--max-lines 600] [PATH ...]

A report, not a gate: it lists what exceeds the limits (CONVENTIONS: no function above 20, no
module above 600 lines without a reason stated in its docstring) and exits 0. A function's
complexity is radon's, as `radon cc -s` gives it; closures, which `radon cc` leaves out by
default, are listed under their enclosing function's name. A module's length is its physical
lines (radon's `loc`).
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from radon.complexity import cc_visit
from radon.raw import analyze
from radon.visitors import Function

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hil", "controllers", "rigbus", "robots")
MAX_COMPLEXITY = 20
MAX_LINES = 600


@dataclass(frozen=True)
class Complex:
    """A function above the complexity limit: where it is, its qualified name, its complexity."""

    path: str
    line: int
    name: str
    complexity: int


@dataclass(frozen=True)
class Long:
    """A module above the length limit [lines]."""

    path: str
    lines: int


def python_files(paths: Iterable[Path]) -> list[Path]:
    """Every .py file under `paths` (files are taken as they are), sorted."""
    found: set[Path] = set()
    for path in paths:
        if path.is_dir():
            found.update(p for p in path.rglob("*.py") if "__pycache__" not in p.parts)
        else:
            found.add(path)
    return sorted(found)


def _functions(blocks: Iterable[object], outer: str = "") -> Iterator[tuple[str, Function]]:
    """(qualified name, function) of radon's blocks: functions, methods and their closures."""
    for block in blocks:
        if not isinstance(block, Function):
            continue  # a class: its methods are blocks of their own
        name = f"{outer}.{block.name}" if outer else block.fullname
        yield name, block
        yield from _functions(block.closures, name)


def _shown(file: Path, root: Path) -> str:
    """`file` relative to `root` where it is under it."""
    try:
        return file.resolve().relative_to(root).as_posix()
    except ValueError:
        return file.as_posix()


def report(
    paths: Iterable[Path],
    root: Path = ROOT,
    max_complexity: int = MAX_COMPLEXITY,
    max_lines: int = MAX_LINES,
) -> tuple[list[Complex], list[Long]]:
    """The functions above `max_complexity`, most complex first, and the modules above
    `max_lines`, longest first, of the Python files under `paths` (named relative to `root`)."""
    complex_functions: list[Complex] = []
    long_modules: list[Long] = []
    for file in python_files(paths):
        text = file.read_text(encoding="utf-8")
        shown = _shown(file, root)
        for name, function in _functions(cc_visit(text)):
            if function.complexity > max_complexity:
                complex_functions.append(Complex(shown, function.lineno, name, function.complexity))
        lines = analyze(text).loc
        if lines > max_lines:
            long_modules.append(Long(shown, lines))
    complex_functions.sort(key=lambda c: (-c.complexity, c.path, c.line))
    long_modules.sort(key=lambda m: (-m.lines, m.path))
    return complex_functions, long_modules


def format_report(
    complex_functions: Sequence[Complex],
    long_modules: Sequence[Long],
    max_complexity: int = MAX_COMPLEXITY,
    max_lines: int = MAX_LINES,
) -> str:
    """The report as text: one line a function or module, under a heading with its count."""
    out = [f"functions above cyclomatic complexity {max_complexity}: {len(complex_functions)}"]
    out += [f"  {c.complexity:4d}  {c.path}:{c.line}  {c.name}" for c in complex_functions]
    out.append(f"modules above {max_lines} lines: {len(long_modules)}")
    out += [f"  {m.lines:4d}  {m.path}" for m in long_modules]
    return "\n".join(out) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tests.complexity",
        description="List functions above a cyclomatic complexity (radon) and modules above a "
        "length; a report, it exits 0.",
    )
    parser.add_argument(
        "paths",
        nargs="*",
        type=Path,
        help=f"files or folders (default: {', '.join(PACKAGES)} of this checkout)",
    )
    parser.add_argument(
        "--max-complexity", type=int, default=MAX_COMPLEXITY, help="(default: %(default)s)"
    )
    parser.add_argument("--max-lines", type=int, default=MAX_LINES, help="(default: %(default)s)")
    args = parser.parse_args(argv)
    paths = args.paths or [ROOT / p for p in PACKAGES]
    found = report(paths, ROOT, args.max_complexity, args.max_lines)
    print(format_report(*found, args.max_complexity, args.max_lines), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
