"""The run's loops with the heap built before them frozen (rigbus/heap.py): a full collection
in the loop traverses only what the loop made, and nothing stays frozen after it."""

from __future__ import annotations

import gc
import weakref
from pathlib import Path

import pytest

from rigbus.heap import frozen_heap
from tests.helpers import run_summary, scenario_variant


def test_the_heap_is_frozen_inside_and_unfrozen_after_even_on_an_error() -> None:
    before = object()  # an object made before the block: frozen inside it
    assert gc.get_freeze_count() == 0
    with frozen_heap():
        assert gc.get_freeze_count() > 0
        assert gc.is_tracked([before])
    assert gc.get_freeze_count() == 0
    with pytest.raises(RuntimeError), frozen_heap():
        raise RuntimeError("a failed run")
    assert gc.get_freeze_count() == 0


def test_nested_blocks_unfreeze_at_the_outermost_exit_only() -> None:
    """The in-process loop: the plant's block around the controller's. (The count of frozen
    objects may fall inside: a frozen object whose last reference goes is freed.)"""
    with frozen_heap():
        assert gc.get_freeze_count() > 0
        with frozen_heap():
            assert gc.get_freeze_count() > 0
        assert gc.get_freeze_count() > 0  # the inner exit left the outer's objects frozen
    assert gc.get_freeze_count() == 0


def test_a_full_collection_in_the_block_leaves_out_what_was_there() -> None:
    """A cycle made before the block is not collected inside it (it is frozen), and is after."""

    class Node:
        other: object

    a, b = Node(), Node()
    a.other, b.other = b, a  # a reference cycle, unreachable once the names go
    alive = weakref.ref(a)
    del a, b
    with frozen_heap():
        gc.collect()
        assert alive() is not None
    gc.collect()
    assert alive() is None


@pytest.mark.parametrize("inprocess", [True, False])
def test_a_run_s_loop_runs_with_the_heap_frozen_and_leaves_it_unfrozen(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, inprocess: bool
) -> None:
    """The plant's loop sees the heap frozen at every SYNC, driven by the controller in its
    thread (Plant.run_driven) or serving it in its own process (Plant.run); nothing stays
    frozen after the run."""
    from hil.plant import Plant

    seen: list[int] = []
    on_sync = Plant._on_sync

    def recorded(self: Plant, cycle: int) -> None:
        seen.append(gc.get_freeze_count())
        on_sync(self, cycle)

    monkeypatch.setattr(Plant, "_on_sync", recorded)
    path = scenario_variant(tmp_path, "default", {"duration": "duration = 0.2"})
    run_summary(path, tmp_path / "run", inprocess=inprocess)
    assert len(seen) == 21 and min(seen) > 0
    assert gc.get_freeze_count() == 0
