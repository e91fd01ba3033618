"""The run's loops with the heap built before them frozen (rigbus/heap.py): a full collection
in the loop traverses only what the loop made, and nothing stays frozen after it."""

from __future__ import annotations

import gc
import weakref

import pytest

from rigbus.heap import frozen_heap


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
    """The in-process loop: the plant's block around the controller's."""
    with frozen_heap():
        frozen = gc.get_freeze_count()
        with frozen_heap():
            assert gc.get_freeze_count() >= frozen
        assert gc.get_freeze_count() >= frozen > 0  # the inner exit left the outer's frozen
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
