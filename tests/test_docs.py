"""The docs stand on the code: every file or folder docs/*.md names exists, and the SYNC trace
(docs/sync-cycle.md, "The trace") names at most ten files, as a newcomer reads it."""

from __future__ import annotations

import re
from pathlib import Path

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
