"""bench/instructions.py: instructions per SYNC from callgrind's report (the run itself needs
valgrind and minutes, so the suite checks how its figure is made, not a run)."""

from __future__ import annotations

import pytest

from bench.instructions import TOGGLE_C, instructions_per_sync

REPORT = """==4242== Callgrind, a call-graph generating cache profiler
==4242== Events    : Ir
==4242== Collected : 1290700000
==4242==
==4242== I   refs:      1,290,700,000
"""


def test_instructions_per_sync_from_the_collected_line() -> None:
    assert instructions_per_sync(REPORT, 101) == 1_290_700_000 / 101
    # the last report counts (a child that exited first printed its own)
    earlier = REPORT.replace("4242", "4241").replace("1290700000", "5")
    assert instructions_per_sync(earlier + REPORT, 101) == instructions_per_sync(REPORT, 101)


@pytest.mark.parametrize(
    ("text", "syncs", "message"),
    [("no report at all", 10, "no 'Collected'"), (REPORT, 0, "ran 0 SYNCs")],
)
def test_a_run_without_a_count_is_an_error(text: str, syncs: int, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        instructions_per_sync(text, syncs)


def test_collection_is_toggled_by_callgrinds_client_request() -> None:
    assert "#include <valgrind/callgrind.h>" in TOGGLE_C
    assert "CALLGRIND_TOGGLE_COLLECT" in TOGGLE_C
