"""Curvature estimators behind the `Estimator` contract, by name: `raw` (geometric inversion,
here), `kf` (a linear Kalman filter per segment: controllers.segment_kf) and `ukf` (an unscented
Kalman filter on the whole arm: controllers.arm_ukf); `make_estimator` makes one, `run_offline`
feeds it a recorded run.

The filters' models (the bend ODE discretised exactly, the unmodelled torque and the markers'
noise derived from the rig, nothing tuned by hand), their outlier gate and their latency
compensation (each picture fused at its exposure time) are in controllers.bend_filter.

Invariant: an estimate depends only on the sequence of `update` calls (bit-identical reruns).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from controllers.arm_ukf import ArmUnscentedEstimator
from controllers.estimation import (
    BendModel,
    CameraNoise,
    DriveReading,
    Estimate,
    Estimator,
    MarkerFrame,
)
from controllers.kinematics import curvatures_from_markers
from controllers.segment_kf import SegmentKalmanEstimator

NAMES = ("raw", "kf", "ukf")


class RawEstimator:
    """Today's geometric inversion: the newest complete frame (every marker seen) through
    `curvatures_from_markers`, held until the next; the rate is the finite difference between
    successive complete frames over their exposure times. No model, so no latency compensation
    and no standard deviation (NaN)."""

    name = "raw"

    def __init__(self, bends: Sequence[BendModel], base: tuple[float, float, float]) -> None:
        self.lengths = [b.length for b in bends]
        self.base = base
        n = len(bends)
        self.kappa = np.zeros(n)
        self.kappa_rate = np.zeros(n)
        self._exposure: float | None = None

    def update(
        self, t: float, drives: Mapping[int, DriveReading], frames: Sequence[MarkerFrame]
    ) -> Estimate:
        measured = 0
        for frame in frames:
            if not frame.seen.all():
                continue
            kappa = curvatures_from_markers(frame.points[:, :2], self.lengths, self.base[2])
            if self._exposure is not None and frame.exposure_time > self._exposure:
                self.kappa_rate = (kappa - self.kappa) / (frame.exposure_time - self._exposure)
            self.kappa, self._exposure = kappa, frame.exposure_time
            measured += len(kappa)
        nan = np.full(len(self.kappa), np.nan)
        return Estimate(self.kappa.copy(), self.kappa_rate.copy(), nan, 0, measured)


def make_estimator(
    name: str,
    bends: Sequence[BendModel],
    base: tuple[float, float, float],
    camera: CameraNoise,
    control_period: float,
    latency_compensation: bool = True,
    torque_std: float | None = None,
    masses: Sequence[float] | None = None,
) -> Estimator:
    """The estimator called `name` ("raw", "kf" or "ukf").

    Parameters
    ----------
    name
        Which estimator.
    bends
        One bend model per segment, base to tip, shape (N,).
    base
        Base pose: x [m], y [m], heading [rad].
    camera
        What the controller knows of its camera (noise, rate, latency).
    control_period
        T [s]: the SYNC period, over which the unmodelled torque is held.
    latency_compensation
        Fuse each picture at its exposure time (True) or at the SYNC time (False).
    torque_std
        Unmodelled torque standard deviation [N m]; None derives it per segment
        (`unmodelled_torque_std`).
    masses
        The segments' masses [kg] where the bends are one multibody arm: `ukf` predicts them
        coupled by the arm's mass matrix at the estimated configuration
        (`controllers.kinematics.mass_matrix`), `kf` (one filter per segment) each with the
        inertia its bend carries in the straight arm (the bends' `inertia`); None: each bend
        alone with its own inertia.
    """
    if name == "raw":
        return RawEstimator(bends, base)
    if name == "kf":
        return SegmentKalmanEstimator(
            bends, base, camera, control_period, latency_compensation, torque_std
        )
    if name == "ukf":
        return ArmUnscentedEstimator(
            bends, base, camera, control_period, latency_compensation, torque_std, masses
        )
    raise ValueError(f"unknown estimator {name!r}: choose one of {', '.join(NAMES)}")


@dataclass(frozen=True)
class OfflineEstimates:
    """Estimates over a run: kappa and kappa_std shape (cycles, N) [1/m]; counts shape (cycles,)."""

    kappa: np.ndarray
    kappa_std: np.ndarray
    gated: np.ndarray
    measured: np.ndarray


def run_offline(
    estimator: Estimator,
    cycles: Iterable[tuple[float, Mapping[int, DriveReading], Sequence[MarkerFrame]]],
) -> OfflineEstimates:
    """Feed recorded cycles (SYNC time [s], drive readings, camera frames) to `estimator`."""
    estimates = [estimator.update(t, drives, frames) for t, drives, frames in cycles]
    return OfflineEstimates(
        np.array([e.kappa for e in estimates]),
        np.array([e.kappa_std for e in estimates]),
        np.array([e.gated for e in estimates], dtype=int),
        np.array([e.measured for e in estimates], dtype=int),
    )
