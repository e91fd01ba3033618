"""The camera's picture in C (`_cvision.c`): its draws and points in one call.

`hil.vision.Camera.picture` draws each marker's noise, dropout and outlier from numpy random
streams and adds them up in some fifteen numpy calls, 11.5 us a picture (4.1 us in C), most of
it the calls' own cost on a handful of values. The C module makes the same draws through numpy's
C random API (numpy ships it for this: `numpy/random/lib/libnpyrandom.a`, the functions its
Generator calls) on the same bit generators, so pictures and streams are the same bit for bit
(tests/test_vision.py compares them with the numpy path over seeds, effects and shapes).

It is built with `$CC` (or gcc) against this Python's headers and numpy's random API into the
softhil cache, keyed by numpy's version. Without a compiler, the headers or numpy's archive, or
with ``SOFTHIL_CAMERA=python``, the camera draws through numpy's Python API (`failure()` says why):
the same pictures.
"""

from __future__ import annotations

import logging
from pathlib import Path
from types import ModuleType

import numpy as np

from rigbus.cbuild import (
    LIBRARY_FLAGS,
    CompileError,
    CPart,
    compile_extension,
    load_extension,
)

SOURCE = Path(__file__).with_name("_cvision.c")
MODULE = "_softhil_cvision"
ENV = "SOFTHIL_CAMERA"  # "python": pictures drawn through numpy's Python API only


def _numpy_random() -> tuple[Path, Path]:
    """numpy's C headers and its random API's static archive; CompileError if either is not
    shipped with this numpy."""
    root = Path(np.__file__).parent
    include = Path(np.get_include())
    archive = root / "random" / "lib" / "libnpyrandom.a"
    if not (include / "numpy" / "random" / "bitgen.h").is_file() or not archive.is_file():
        raise CompileError(f"numpy {np.__version__} ships no C random API (libnpyrandom.a)")
    return include, archive


def _build() -> Path:
    include, archive = _numpy_random()
    return compile_extension(
        "vision",
        "cvision",
        SOURCE,
        (*LIBRARY_FLAGS, f"-I{include}"),
        link=(str(archive), "-lm"),
        salt=f"numpy {np.__version__} {archive.stat().st_size}",
    )


_part: CPart[ModuleType] = CPart(
    ENV,
    "pictures drawn in C where it builds",
    lambda: load_extension(MODULE, _build),
    logging.getLogger(__name__),
    "camera pictures are drawn through numpy's Python API (slower, the same pictures)",
)


# the C part's interface: `setting()` its variable's value ("c" or "python"; ValueError naming
# it for any other), `load()` the part (built if needed; None if it cannot be) and `failure()`
# why it is not in use (None: it is, or it was not tried yet)
setting = _part.setting
load = _part.get
failure = _part.why
