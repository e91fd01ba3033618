"""python-can, imported without paying for its MF4 support until an MF4 log is opened.

`import can` (python-can 4.x) imports `can.io.mf4`, which imports asammdf when it is installed,
and asammdf imports pandas and sympy: 1.6-1.9 s of a process's start on this project's machines
against 0.17 s without it (python-can issue #935). Every softhil process imports python-can (the
controller, the plant, each `hil` command), and the test suite starts hundreds of them, while
only the bus tools' `.mf4` logs and `[recording] mf4` ever need asammdf.

`import_can()` imports python-can with asammdf hidden, then makes its MF4 reader and writer
finish the import the first time one is made: `can.io.mf4` is re-executed in its own namespace
once asammdf is imported, so the classes python-can already handed out (`can.MF4Writer`, the
writer `can.Logger` picks by suffix) see asammdf from then on. Without asammdf installed they
fail as python-can's own do. Where python-can was imported before this (a user's program that
imported `can` first), it is left as it is.

`rigbus/__init__.py` calls it, so importing any part of softhil first is enough.
"""

from __future__ import annotations

import importlib
import sys
from types import ModuleType
from typing import Any

_MF4 = "can.io.mf4"


def import_can() -> ModuleType:
    """python-can, imported now without asammdf if nothing imported it yet."""
    if "can" in sys.modules or "asammdf" in sys.modules:
        import can  # imported already, or asammdf is loaded anyway: nothing to save

        return can
    sys.modules["asammdf"] = None  # type: ignore[assignment]  # `import asammdf` -> ImportError
    try:
        import can
    finally:
        del sys.modules["asammdf"]
    mf4 = sys.modules[_MF4]
    if getattr(mf4, "asammdf", None) is None:
        for cls in (mf4.MF4Reader, mf4.MF4Writer):
            _load_on_first_use(cls)
    return can


def mf4_loaded() -> bool:
    """Whether python-can's MF4 reader and writer have asammdf to work with."""
    mf4 = sys.modules.get(_MF4)
    return mf4 is not None and getattr(mf4, "asammdf", None) is not None


def load_mf4() -> bool:
    """Finish python-can's MF4 import (asammdf) now; False if asammdf is not installed."""
    mf4 = sys.modules.get(_MF4)
    if mf4 is None:
        import_can()
        mf4 = sys.modules[_MF4]
    if getattr(mf4, "asammdf", None) is not None:
        return True
    try:
        import asammdf  # noqa: F401
    except ImportError:
        return False
    # the same namespace, executed again: the classes handed out before keep working in it
    importlib.reload(mf4)
    return True


def _load_on_first_use(cls: type) -> None:
    original = cls.__init__  # type: ignore[misc]

    def init(self: Any, *args: Any, **kwargs: Any) -> None:
        load_mf4()
        original(self, *args, **kwargs)

    init.__doc__ = original.__doc__
    init.__wrapped__ = original  # type: ignore[attr-defined]
    cls.__init__ = init  # type: ignore[misc]
