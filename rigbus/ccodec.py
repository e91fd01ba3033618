"""The DBC codec's plain case in C (`_ccodec.c`), built on first use with the FMU toolchain.

`rigbus.protocol._Codec` encodes and decodes through it when it is available: a frame's
values to bytes and a payload to its typed frame in one C call each (a DriveStatus: about 0.5 us
each way, against 3-4 us for the generated Python codec and 14 us for cantools' encode). It
handles the plain case only (every value present, a float, int or bool, finite and in range; a
payload whose index matches) and returns None for anything else, which the Python codec then
encodes or rejects with the error it always gave: results and errors are the same bit for bit.

The module is compiled with `$CC` (or gcc) against this Python's headers into the softhil cache
(`rigbus.cbuild`, shared with the plant's kernel: the controller never imports `hil`),
keyed by a digest of the source, the flags, the compiler and the Python ABI, and loaded from
there. Without a compiler or the headers, or with
``SOFTHIL_CODEC=python``, the Python codec does everything (`available()` says which).
"""

from __future__ import annotations

import logging
from pathlib import Path
from types import ModuleType

from rigbus.cbuild import (
    LIBRARY_FLAGS,
    CPart,
    compile_extension,
    load_extension,
)

SOURCE = Path(__file__).with_name("_ccodec.c")
MODULE = "_softhil_ccodec"
FLAGS = LIBRARY_FLAGS
ENV = "SOFTHIL_CODEC"  # "python": never use the C codec


def _build() -> Path:
    """The module in the softhil cache, compiled if it is not there (CompileError if it cannot
    be: no compiler, no Python.h, a compiler error)."""
    return compile_extension("codec", "ccodec", SOURCE, FLAGS)


_part: CPart[ModuleType] = CPart(
    ENV,
    "the C codec where it builds",
    lambda: load_extension(MODULE, _build),
    logging.getLogger(__name__),
    "the DBC codec runs in Python only (slower, same frames)",
)


# the C part's interface: `setting()` its variable's value ("c" or "python"; ValueError naming
# it for any other), `load()` the part (built if needed; None if it cannot be) and `failure()`
# why it is not in use (None: it is, or it was not tried yet)
setting = _part.setting
load = _part.get
failure = _part.why
