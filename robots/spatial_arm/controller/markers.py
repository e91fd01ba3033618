"""The spatial arm's markers and their Jacobian at one configuration, for the controller's loop:
in C (`_markers.c`, complex-step derivatives) where it builds, else through `kinematics` (the
same numbers to rounding; tests/test_spatial_arm.py compares them). The batch mathematics of
`kinematics` serves planning and drawing; at one configuration its many small array operations
cost about 1.2 ms, the C part a few microseconds, which is what lets the loop run many times
faster than real time.
"""

from __future__ import annotations

import logging
from pathlib import Path
from types import ModuleType

import numpy as np

from rigbus.cbuild import LIBRARY_FLAGS, CPart, compile_extension, load_extension
from robots.spatial_arm.controller import kinematics
from robots.spatial_arm.controller.model import ArmModel

SOURCE = Path(__file__).with_name("_markers.c")
MODULE = "_spatial_markers"
ENV = "SOFTHIL_SPATIAL_MARKERS"  # "python": never use the C part


def _build() -> Path:
    return compile_extension("spatial", "spatial_markers", SOURCE, LIBRARY_FLAGS)


_part: CPart[ModuleType] = CPart(
    ENV,
    "the spatial arm's markers in C where they build",
    lambda: load_extension(MODULE, _build),
    logging.getLogger(__name__),
    "the spatial arm's markers run through numpy (slower, the same values)",
)
load = _part.get


class Markers:
    """markers(q) and their Jacobian for one arm (planar arms through `kinematics`)."""

    def __init__(self, model: ArmModel) -> None:
        self.model = model
        self.n = model.n_segments
        self.L = np.ascontiguousarray(model.L, dtype=float)
        self.L_p = np.ascontiguousarray(model.L_p, dtype=float)
        self.module = None if model.planar else load()

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The base origin and every endplate (N + 1, 3) and their derivatives (N + 1, 3, n_q)."""
        if self.module is None:
            m, J = kinematics.marker_jacobian(self.model, np.asarray(q, dtype=float))
            return np.asarray(m), np.asarray(J)
        out_m = np.empty((self.n + 1, 3))
        out_J = np.empty((self.n + 1, 3, 2 * self.n))
        self.module.markers(self.L, self.L_p, np.ascontiguousarray(q, dtype=float), out_m, out_J)
        return out_m, out_J
