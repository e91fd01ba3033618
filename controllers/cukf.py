"""The arm UKF's prediction and correction in C (`_cukf.c`), built on first use with the FMU
toolchain and called through ctypes.

`controllers.arm_ukf.ArmUnscentedEstimator` predicts and corrects through it when it is
available: one C call each (about 3 us for the correction on six segments, against about 120 us
for the same maths in numpy, which is the reference and the fallback). The results agree with
numpy's to rounding (tests/test_cukf.py), not bit for bit: numpy's BLAS picks its own order of
sums and uses fused multiply-adds where the CPU has them, so numpy's bits differ between hosts,
while this code, built with -ffp-contract=off, gives the same bits on every one.

The library is compiled with `$CC` (or gcc) into the softhil cache (`rigbus.cbuild`, keyed
by a digest of the source, the flags and the compiler) and loaded from there. Without a
compiler, or with ``SOFTHIL_UKF=python``, numpy does everything (`failure()` says why).
"""

from __future__ import annotations

import ctypes
import logging
from pathlib import Path

from rigbus.cbuild import LIBRARY_FLAGS, CPart, compile_library

SOURCE = Path(__file__).with_name("_cukf.c")
FLAGS = (*LIBRARY_FLAGS, "-lm")
ENV = "SOFTHIL_UKF"  # "python": the UKF in numpy only

_Ptr = ctypes.POINTER(ctypes.c_double)


class Workspace(ctypes.Structure):
    """`struct softhil_ukf` of _cukf.c: sizes, constants and the caller's buffers."""

    _fields_ = [
        ("segments", ctypes.c_int),
        ("spread", ctypes.c_double),
        ("noise", ctypes.c_double),
        ("gate", ctypes.c_double),
        ("base", ctypes.c_double * 3),
        ("lengths", _Ptr),
        ("Wm", _Ptr),
        ("Wc", _Ptr),
        ("x", _Ptr),
        ("P", _Ptr),
        ("points", _Ptr),
        ("F", _Ptr),
        ("G", _Ptr),
        ("Q", _Ptr),
        ("u", _Ptr),
        ("x_out", _Ptr),
        ("P_out", _Ptr),
        ("y", _Ptr),
        ("S", _Ptr),
        ("gated", ctypes.c_int),
        ("measured", ctypes.c_int),
        ("work", _Ptr),
    ]


def work_size(segments: int) -> int:
    """Doubles the C code's `work` buffer needs for `segments` segments."""
    n = 2 * segments
    return (2 * n + 1) * (n + 4 * segments) + 4 * segments + 24 * segments**2 + 16


def _load() -> ctypes.CDLL:
    """The library from the softhil cache, compiled if it is not there; a cached file that does
    not load is built again."""
    path = compile_library("ukf", "cukf", SOURCE, FLAGS)
    try:
        library = ctypes.CDLL(str(path))
    except OSError:  # a damaged cache entry: built again
        path.unlink()
        library = ctypes.CDLL(str(compile_library("ukf", "cukf", SOURCE, FLAGS)))
    for name in ("softhil_ukf_predict", "softhil_ukf_correct"):
        function = getattr(library, name)
        function.argtypes = [ctypes.POINTER(Workspace)]
        function.restype = ctypes.c_int
    return library


_part: CPart[ctypes.CDLL] = CPart(
    ENV,
    "the UKF's algebra in C where it builds",
    _load,
    logging.getLogger(__name__),
    "the UKF runs in numpy only (slower, the same to rounding)",
    " (numpy)",
)


# the C part's interface: `setting()` its variable's value ("c" or "python"; ValueError naming
# it for any other), `load()` the part (built if needed; None if it cannot be) and `failure()`
# why it is not in use (None: it is, or it was not tried yet)
setting = _part.setting
load = _part.get
failure = _part.why
