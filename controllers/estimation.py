"""The controller side's contracts: what an estimator sees and returns, and what a controller does.

A controller program is a bus loop (`controllers.node`) around two pure pieces of computation:

- an `Estimator` turns measurements into the robot's configuration. Each control cycle it is
  given the cycle's SYNC time, the drive status of that cycle (piston position and both chamber
  pressures per drive, sampled at the SYNC), and the camera frames that were completed in the
  cycle, each with the time its picture was taken (its exposure time, always before the SYNC
  time: the camera is late). It returns an `Estimate` valid at the SYNC time.
- a `Controller` turns references and the estimate into actuator commands.

Neither does I/O, so a recorded CAN log can drive them offline (the estimation report, `hil
estimate`, CAN-log replay) and a test can drive them with synthetic data. Invariant: an
estimator's output depends only on the sequence of calls made to it (no clock, no global state,
no unseeded randomness), so runs are deterministic.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np


@dataclass(frozen=True, slots=True)
class DriveReading:
    """One drive's status as sampled at a SYNC (the DriveStatus frame), SI units."""

    piston_position: float  # [m]
    p_a: float  # [Pa gauge]
    p_b: float  # [Pa gauge]
    fault: int = 0


@dataclass(frozen=True, slots=True)
class MarkerFrame:
    """One camera picture: marker positions at `exposure_time`.

    `points` has shape (markers, dims) with dims 2 (planar) or 3; a marker the camera did not see
    in this picture (dropout, occlusion) is a row of NaN. Marker 0 is the base; marker i the end
    of segment i."""

    exposure_time: float  # [s] simulation time at which the picture was taken
    points: np.ndarray

    @property
    def seen(self) -> np.ndarray:
        """Boolean mask of the markers present in this picture, shape (markers,)."""
        return ~np.isnan(self.points).any(axis=1)


@dataclass(frozen=True, slots=True)
class Estimate:
    """The configuration at a SYNC time: per-segment curvature [1/m], its rate [1/(m s)] and the
    standard deviation of the curvature estimate [1/m] (NaN where an estimator has none)."""

    kappa: np.ndarray
    kappa_rate: np.ndarray
    kappa_std: np.ndarray
    gated: int = 0  # camera measurements rejected as outliers in this update
    measured: int = 0  # camera measurements accepted in this update
    objects: np.ndarray | None = None  # estimated object centres, shape (k, 2) [m] (NaN: unseen)


@dataclass(frozen=True)
class BendModel:
    """What the controller knows of one segment's bending (fmus/FeaSegment/model.c):
    `inertia theta'' + d_bend theta' + k_bend theta = G_a (h(p_a) - h(p_b))`, theta = kappa *
    length, where h(g) = g under pressure and, under vacuum, the collapsing channel's
    h(g) = beta g + (1 - beta) p_c (exp(g / p_c) - 1) (beta = vacuum_factor, p_c = p_collapse):
    the FeaSegment FMU's torque law."""

    length: float  # [m]
    inertia: float  # [kg m^2]
    k_bend: float  # [N m/rad]
    d_bend: float  # [N m s/rad]
    G_a: float  # [m^3/rad]
    theta_max: float = 1.6  # [rad]
    vacuum_factor: float = 1.0  # share of G_a left under deep vacuum (1: no collapse)
    p_collapse: float = 1e4  # [Pa] vacuum over which the channel collapses
    # [kg] the segment's own mass (its table friction); 0: the lone segment's, 20 inertia / L^2
    # (in a multibody arm `inertia` is the whole outer arm's, the diagonal of its mass matrix)
    mass: float = 0.0

    def effective_pressure(self, gauge: float) -> float:
        """h(g) [Pa]: the pressure that, times G_a, is the channel's torque."""
        if gauge >= 0.0:
            return gauge
        beta, pc = self.vacuum_factor, self.p_collapse
        return beta * gauge + (1.0 - beta) * pc * math.expm1(gauge / pc)


@dataclass(frozen=True)
class CameraNoise:
    """What the controller is told of its camera (the scenario's [camera] section): it sets the
    estimators' measurement noise and outlier gate, never a hand-tuned constant."""

    noise: float = 0.0  # isotropic marker position standard deviation [m]
    dropout: float = 0.0  # per-marker probability of a missing marker
    outlier_rate: float = 0.0  # per-marker probability of a displaced marker
    outlier_distance: float = 0.0  # displacement of an outlier [m]
    rate: float = 100.0  # [Hz]
    latency: float = 0.0  # exposure to availability [s]


class Estimator(Protocol):
    """Configuration from measurements; see the module docstring."""

    name: str

    def update(
        self,
        t: float,
        drives: Mapping[int, DriveReading],
        frames: Sequence[MarkerFrame],
    ) -> Estimate:
        """The estimate at SYNC time `t` [s] from this cycle's drive readings (by drive node
        1..N) and the camera frames completed in this cycle (oldest first)."""
        ...


class Controller(Protocol):
    """Commands from the task and the estimate: the frames to send this cycle (actuator commands
    acting from the next SYNC, and the controller-state frames that report reference and
    estimate for recording and replay)."""

    def compute(
        self,
        cycle: int,
        t: float,
        estimate: Estimate,
        drives: Mapping[int, DriveReading],
    ) -> list[Any]: ...
