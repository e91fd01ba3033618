"""The environment variables that change how softhil computes (never what): each is checked
where it is read, and all of them once when `hil` starts, so that a misspelt value is one line
naming the variable instead of a silent default."""

from __future__ import annotations

import os

from hil.errors import HilError

KERNEL = "SOFTHIL_KERNEL"  # "0": step FMUs in Python; "1" (the default): the C kernel


def kernel_enabled() -> bool:
    """SOFTHIL_KERNEL as a switch: unset or "1" on, "0" off; HilError for any other value."""
    value = os.environ.get(KERNEL, "1").strip()
    if value not in ("0", "1"):
        raise HilError(
            f"{KERNEL}={os.environ[KERNEL]!r}: must be 1 (step FMUs in the C kernel, the "
            "default) or 0 (in Python)"
        )
    return value == "1"


def check() -> None:
    """HilError naming the first softhil variable whose value is not one softhil reads."""
    from controllers import ccodec

    kernel_enabled()
    try:
        ccodec.setting()
    except ValueError as exc:
        raise HilError(str(exc)) from None
