"""`kf`: a linear Kalman filter per segment of the arm (controllers.bend_filter: the models, the
outlier gate and the latency compensation it shares with `ukf`).

Invariant: an estimate depends only on the sequence of `update` calls (bit-identical reruns).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from filterpy.kalman import KalmanFilter
from scipy.stats import chi2

from controllers.bend_filter import GATE_PROBABILITY, REACQUIRE, LatencyFilter
from controllers.estimation import BendModel, CameraNoise
from controllers.fast_linalg import einsum


class SegmentKalmanEstimator(LatencyFilter):
    """One linear Kalman filter (filterpy) per segment on (theta, omega), measuring the segment's
    curvature from the chord angle of its two end markers. The filters' predictions are batched
    over the segments in numpy (the same F x + G u, F P F' + Q, without a call per segment).

    Start heading: a segment's measurement kappa = 2 (alpha - th0) / L needs th0, the heading at
    its start. It is taken from the filters' own prior at the exposure time (base heading plus
    the predicted bend angles of the segments before it), not from the markers, so a segment
    whose two markers are seen updates even when markers nearer the base are missing, and an
    outlier near the base does not leak into every later segment. Its uncertainty enters R:
    R = (2/L)^2 (var(alpha) + sum over earlier segments of var(theta_j)), var(alpha) =
    2 sigma^2 / chord^2 (the cross-chord noise of two markers), treating the segments'
    errors as independent. They are not: a segment's error is anti-correlated with the heading
    error of the segments before it, so on segments 2.. the innovations come out smaller than S
    says (NIS about 0.8) and the reported standard deviation about 1.4x too small. `ukf`, which
    carries these correlations, has neither defect."""

    name = "kf"

    def __init__(
        self,
        bends: Sequence[BendModel],
        base: tuple[float, float, float],
        camera: CameraNoise,
        control_period: float,
        latency_compensation: bool = True,
        torque_std: float | None = None,
    ) -> None:
        super().__init__(bends, base, camera, control_period, latency_compensation, torque_std)
        self.filters = [KalmanFilter(dim_x=2, dim_z=1) for _ in self.bends]
        self.gate = float(chi2.ppf(GATE_PROBABILITY, 1))
        self.rejected = np.zeros(self.segments, int)  # consecutive gated measurements

    def _initial(self) -> tuple[np.ndarray, np.ndarray]:
        var_theta, var_omega = self._initial_variances()
        x = np.zeros((self.segments, 2))
        P = np.zeros((self.segments, 2, 2))
        P[:, 0, 0], P[:, 1, 1] = var_theta, var_omega
        return x, P

    def _predict(
        self, x: np.ndarray, P: np.ndarray, u: np.ndarray, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        # the filters' prediction x = F x + G u, P = F P F' + Q, batched over the segments
        F, G, Q = (np.stack(m) for m in zip(*(d(dt) for d in self.discretisers), strict=True))
        x = einsum("nij,nj->ni", F, x) + G * u[:, np.newaxis]
        P = einsum("nij,njk,nlk->nil", F, P, F) + Q
        return x, P

    def _correct(
        self, x: np.ndarray, P: np.ndarray, points: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, int, int]:
        seen = ~np.isnan(points).any(axis=1)
        prior_theta = x[:, 0].copy()
        prior_var = P[:, 0, 0].copy()
        x, P = x.copy(), P.copy()
        gated = measured = 0
        innovations, variances = [], []
        heading, heading_var = self.base[2], 0.0
        for i, (kf, length) in enumerate(zip(self.filters, self.lengths, strict=True)):
            if seen[i] and seen[i + 1]:
                dx, dy = points[i + 1] - points[i]
                half = math.remainder(math.atan2(dy, dx) - heading, 2.0 * math.pi)
                z = 2.0 * half / length
                half_prior = 0.5 * prior_theta[i]
                chord = length * (math.sin(half_prior) / half_prior if half_prior else 1.0)
                alpha_var = 2.0 * self.sigma**2 / chord**2
                R = (2.0 / length) ** 2 * (alpha_var + heading_var)
                H = np.array([[1.0 / length, 0.0]])
                S = float((H @ P[i] @ H.T)[0, 0]) + R
                y = z - x[i, 0] / length
                if y * y / S > self.gate and self.rejected[i] + 1 < REACQUIRE:
                    gated += 1
                    self.rejected[i] += 1
                else:
                    if self.rejected[i] + 1 >= REACQUIRE and y * y / S > self.gate:
                        # the model has lost the segment (a load it does not know, such as a
                        # held object): forget the prior and take the camera's word again
                        var_theta, var_omega = self._initial_variances()
                        P[i] = P[i] + np.diag([var_theta[i], var_omega[i]])
                        S = float((H @ P[i] @ H.T)[0, 0]) + R
                    self.rejected[i] = 0
                    kf.x, kf.P = x[i].reshape(2, 1), P[i]
                    kf.update(np.array([[z]]), R=np.array([[R]]), H=H)
                    x[i], P[i] = kf.x.ravel(), kf.P
                    innovations.append(float(kf.y[0, 0]))
                    variances.append(float(kf.S[0, 0]))
                    measured += 1
            heading += prior_theta[i]
            heading_var += prior_var[i]
        if innovations:
            self.innovation = np.array(innovations)
            self.innovation_covariance = np.diag(variances)
        return x, P, gated, measured

    def _read(self, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return x[:, 0], x[:, 1], P[:, 0, 0]
