"""numpy's linear algebra kernels called without their wrapping: the same LAPACK calls, so the
same results bit for bit as `np.einsum`, `np.linalg.inv` and `np.linalg.cholesky`, in a fraction
of the time on the filters' small matrices (falling back to the public functions on a numpy that
moved its kernels).
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np

__all__ = ["einsum", "inverse", "robust_sqrt"]

_INV: Any = None
_CHOLESKY: Any = None
einsum: Any = np.einsum  # a numpy that keeps c_einsum elsewhere: the public function
with contextlib.suppress(ImportError):  # what np.einsum calls when not asked to optimise
    from numpy._core.multiarray import c_einsum as einsum
try:  # the kernels behind np.linalg.inv and np.linalg.cholesky: the same LAPACK calls
    from numpy.linalg import _umath_linalg

    _INV, _CHOLESKY = _umath_linalg.inv, _umath_linalg.cholesky_lo
except (ImportError, AttributeError):  # a numpy that moved them: the public functions
    pass


def inverse(S: np.ndarray) -> np.ndarray:
    """np.linalg.inv of a real matrix, bit for bit, without its checks and wrapping (7 us
    instead of 16 on the UKF's 12 x 12); a singular matrix raises np.linalg.LinAlgError."""
    if _INV is not None:
        try:
            with np.errstate(invalid="raise", over="ignore", divide="ignore", under="ignore"):
                return _INV(S, signature="d->d")  # type: ignore[no-any-return]
        except FloatingPointError:
            pass  # singular: np.linalg.inv raises what it raises
    return np.linalg.inv(S)


def robust_sqrt(P: np.ndarray) -> np.ndarray:
    """Upper-triangular square root of a covariance (Cholesky); if rounding made it slightly
    indefinite, the symmetric square root of its positive part instead. The factor is
    np.linalg.cholesky's, bit for bit (its kernel called without the wrapping)."""
    try:
        if _CHOLESKY is None:
            return np.linalg.cholesky(P).T
        with np.errstate(invalid="raise", over="ignore", divide="ignore", under="ignore"):
            return _CHOLESKY(P, signature="d->d").T  # type: ignore[no-any-return]
    except (np.linalg.LinAlgError, FloatingPointError):
        values, vectors = np.linalg.eigh(0.5 * (P + P.T))
        return (vectors * np.sqrt(np.clip(values, 0.0, None))) @ vectors.T
