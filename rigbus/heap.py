"""The garbage collector during a run's loop: the heap built before the loop left out.

CPython's full collection (generation 2) traverses every object it tracks. A plant or a
controller with numpy, scipy, cantools and python-can loaded tracks some 400,000, and one full
collection takes 150-250 ms on a 2-core virtual machine. CPython starts one when the objects
that survived into the oldest generation since the last reach a quarter of it, which a run's
loop reaches or not by chance (the frames a CAN log holds until it writes them survive
there): a 1000-SYNC run of the 6-segment arm measured 165 ms of one such pause inside its loop,
about 165 us per SYNC, and in lockstep the other side waits through it too.

`frozen_heap()` moves every object that exists when the loop starts into the permanent
generation (`gc.freeze`), which collections leave out; the loop's own garbage is collected as
always, and a full collection in the loop traverses only what the loop made. On leaving, the
objects are unfrozen, so a process that runs several loops (a batch's worker, the tests) frees
what the last one left. Nested uses (the in-process loop: the plant serves a controller that
drives the run from the same thread) freeze once and unfreeze at the outermost exit.

Invariant: nothing is ever left frozen once the outermost `frozen_heap` exits, however it exits.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager

_depth = 0  # the frozen_heap blocks entered and not left, in this process


@contextmanager
def frozen_heap() -> Iterator[None]:
    """Collections leave out the objects that exist on entry, until the outermost exit."""
    global _depth
    if _depth == 0:
        gc.freeze()
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if _depth == 0:
            gc.unfreeze()
