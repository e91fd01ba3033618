"""The docs stand on the code: every file or folder docs/*.md names exists, the SYNC trace
(docs/sync-cycle.md, "The trace") names at most ten files, as a newcomer reads it, and no file of
the project cites the developers' private notes (their physics, architecture and conventions
notes, or anything in the folder of shared notes beside the project), which a reader of the
project does not have: a statement points to its source in the project (an FMU's model.c or
model.toml, the README, docs/, code)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").glob("*.md"))
PATH = re.compile(r"`((?:hil|controllers|rigbus|robots|fmus|tests|bench)/[\w./<>-]*)`")


def named(text: str) -> set[str]:
    return {m.group(1) for m in PATH.finditer(text) if "<" not in m.group(1)}


def test_every_path_the_docs_name_exists() -> None:
    assert len(DOCS) >= 3
    for doc in DOCS:
        missing = sorted(p for p in named(doc.read_text()) if not (ROOT / p).exists())
        assert not missing, f"{doc.name}: {missing}"


def test_the_sync_trace_names_at_most_ten_files() -> None:
    text = (ROOT / "docs" / "sync-cycle.md").read_text()
    trace = text.split("## The trace", 1)[1].split("\n## ", 1)[0]
    files = {p for p in named(trace) if not p.endswith("/")}
    assert 8 <= len(files) <= 10, sorted(files)
    assert {"hil/plant.py", "hil/cosim/execution.py", "controllers/node.py"} <= files


# the notes' names, put together here so that this file does not cite them either
PHYS, ARCH, CONV = "PHYS" + "ICS", "ARCHI" + "TECTURE", "CONVEN" + "TIONS"
SHARED = ".." + "/" + "shared"
NOTES = re.compile(rf"\b(?:{PHYS}|{ARCH}|{CONV})\b(?:\.md)?|{re.escape(SHARED)}".encode())


def citations(text: bytes) -> list[tuple[int, str]]:
    """(line number, line) of every line of `text` that cites one of the private notes."""
    return [
        (number, line.decode("utf-8", "replace").strip())
        for number, line in enumerate(text.splitlines(), 1)
        if NOTES.search(line)
    ]


def tracked_files() -> list[Path]:
    """Every file git tracks in the checkout (a test outside a git checkout is skipped)."""
    git = shutil.which("git")
    if git is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: no list of tracked files")
    listed = subprocess.run(
        [git, "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=60
    ).stdout
    return [ROOT / name for name in listed.decode().split("\0") if name]


def test_no_tracked_file_cites_the_private_notes() -> None:
    files = tracked_files()
    assert len(files) > 200
    found = [
        f"{path.relative_to(ROOT)}:{number}: {line}"
        for path in files
        if path.is_file()
        for number, line in citations(path.read_bytes())
    ]
    assert found == [], "\n".join(found)


@pytest.mark.parametrize(
    "line",
    [
        f"Models ({PHYS}.md sections 2, 3, 5)",
        f'"""Device nodes ({ARCH}.md, "Robots")."""',
        f"# Human-facing units ({CONV}: mm and kPa only)",
        f" * see {SHARED}/notes for the derivation",
        f"the order of {PHYS}.md's dead band",
    ],
)
def test_a_citation_of_the_notes_is_found_on_its_line(line: str) -> None:
    text = f"first line\n{line}\nlast line\n".encode()
    assert citations(text) == [(2, line.strip())]


@pytest.mark.parametrize(
    "line",
    [
        "the physics of the segment (fmus/FeaSegment/model.c)",
        "shared/ state",
        f"{PHYS}X",
        f"META{PHYS}.md",
        "./shared",
    ],
)
def test_other_text_is_not_a_citation(line: str) -> None:
    assert citations(line.encode()) == []
