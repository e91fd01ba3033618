"""The environment variables that change how softhil computes (never what): each is checked
where it is read, and all of them once when `hil` starts, so that a misspelt value is one line
naming the variable instead of a silent default."""

from __future__ import annotations

import os

from hil.errors import HilError

KERNEL = "SOFTHIL_KERNEL"  # "0": step FMUs in Python; "1" (the default): the C kernel
# "1": a run with plant and controller in one thread steps the FMUs on the kernel's worker thread
# while the controller computes; "0": in that thread, in turn; unset: on the thread where two
# cores are free and a period costs enough to step (hil.cosim.execution.OVERLAP_MIN_COST)
KERNEL_THREAD = "SOFTHIL_KERNEL_THREAD"
# [s] how long the plant waiting for the worker polls before it sleeps: a job takes 0.1-0.3 ms,
# waking a sleeping thread costs hundreds of microseconds on a virtual machine
KERNEL_THREAD_SPIN = 0.002


def kernel_enabled() -> bool:
    """SOFTHIL_KERNEL as a switch: unset or "1" on, "0" off; HilError for any other value."""
    value = os.environ.get(KERNEL, "1").strip()
    if value not in ("0", "1"):
        raise HilError(
            f"{KERNEL}={os.environ[KERNEL]!r}: must be 1 (step FMUs in the C kernel, the "
            "default) or 0 (in Python)"
        )
    return value == "1"


def kernel_thread() -> bool | None:
    """SOFTHIL_KERNEL_THREAD as a switch: "1" True (always), "0" False (never), unset None
    (where it pays: two cores free, a costly period); HilError for any other value."""
    value = os.environ.get(KERNEL_THREAD)
    if value is None:
        return None
    if value.strip() not in ("0", "1"):
        raise HilError(
            f"{KERNEL_THREAD}={value!r}: must be 1 (step the FMUs on a thread of their own while "
            "the controller computes in this one) or 0 (in turn)"
        )
    return value.strip() == "1"


def two_cores() -> bool:
    """Whether this process may use two cores or more."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return (cores or os.cpu_count() or 1) >= 2


def check() -> None:
    """HilError naming the first softhil variable whose value is not one softhil reads."""
    from hil.seam import cukf
    from rigbus import ccodec

    kernel_enabled()
    kernel_thread()
    try:
        ccodec.setting()
        cukf.setting()
    except ValueError as exc:
        raise HilError(str(exc)) from None
