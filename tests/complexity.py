"""The complexity report: functions above a cyclomatic complexity and modules above a length,
measured by radon (pinned in the `test` extra), in the packages the house holds to them (hil,
controllers, rigbus, robots and the modules of fmus/ itself).

    python -m tests.complexity [--check] [--max-complexity 20] [--max-lines 600] [PATH ...]

The limits: no function above cyclomatic complexity 20, no module above 600 lines without a
reason stated in its docstring. The report lists what exceeds them and exits 0; with --check it
exits 1 when anything breaks them (tests/test_complexity.py holds the house to them). A
function's complexity is radon's, as `radon cc -s` gives it; closures, which `radon cc` leaves
out by default, are listed under their enclosing function's name. A module's length is its
physical lines (radon's `loc`).

A long module's reason is stated when a sentence of its docstring says it is "above 600 lines"
(the limit's number) and gives the reason after a colon or "because", in a few words at least:
"It stays above 600 lines: the DBC's messages are one table, read in one pass."
"""

from __future__ import annotations

import argparse
import ast
import re
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from radon.complexity import cc_visit
from radon.raw import analyze
from radon.visitors import Function

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hil", "controllers", "rigbus", "robots", "fmus/*.py")
MAX_COMPLEXITY = 20
MAX_LINES = 600
REASON_WORDS = 3  # at least, after the colon or "because"


@dataclass(frozen=True)
class Complex:
    """A function above the complexity limit: where it is, its qualified name, its complexity."""

    path: str
    line: int
    name: str
    complexity: int


@dataclass(frozen=True)
class Long:
    """A module above the length limit [lines], and the docstring's sentence stating why ("" if
    there is none)."""

    path: str
    lines: int
    reason: str = ""


def default_paths(root: Path = ROOT) -> list[Path]:
    """The folders and files of PACKAGES under `root` (a pattern names the files it matches)."""
    paths: list[Path] = []
    for package in PACKAGES:
        paths += sorted(root.glob(package)) if "*" in package else [root / package]
    return paths


def stated_reason(text: str, max_lines: int = MAX_LINES) -> str:
    """The sentence of module source `text`'s docstring that says why the module is above
    `max_lines` lines: it says "above {max_lines} lines", then a colon or "because" and at least
    REASON_WORDS words; "" if no sentence does (or the module has no docstring)."""
    try:
        docstring = ast.get_docstring(ast.parse(text)) or ""
    except SyntaxError:
        return ""
    flat = " ".join(docstring.split())
    for sentence in re.split(r"(?<=[.!?])\s+(?=[A-Z(`\"])", flat):
        found = re.search(rf"\babove {max_lines} lines\b[^:]*?(?::|\bbecause\b)(.*)", sentence)
        if found and len(re.findall(r"\w+", found.group(1))) >= REASON_WORDS:
            return sentence
    return ""


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
            long_modules.append(Long(shown, lines, stated_reason(text, max_lines)))
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
    out += [
        f"  {m.lines:4d}  {m.path}" + ("  (reason stated)" if m.reason else "")
        for m in long_modules
    ]
    return "\n".join(out) + "\n"


def breaches(complex_functions: Sequence[Complex], long_modules: Sequence[Long]) -> list[str]:
    """What breaks the limits, a line each: every function above the complexity limit, every
    module above the length limit whose docstring states no reason."""
    out = [f"{c.path}:{c.line} {c.name}: complexity {c.complexity}" for c in complex_functions]
    out += [
        f"{m.path}: {m.lines} lines, no docstring sentence says why it is above the limit"
        for m in long_modules
        if not m.reason
    ]
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tests.complexity",
        description="List functions above a cyclomatic complexity (radon) and modules above a "
        "length; a report, it exits 0 (1 with --check when anything breaks the limits).",
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="exit 1 when a function is above the complexity limit or a module above the length "
        "limit states no reason in its docstring",
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
    paths = args.paths or default_paths()
    found = report(paths, ROOT, args.max_complexity, args.max_lines)
    print(format_report(*found, args.max_complexity, args.max_lines), end="")
    return 1 if args.check and breaches(*found) else 0


if __name__ == "__main__":
    raise SystemExit(main())
