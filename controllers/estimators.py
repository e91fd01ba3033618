"""Curvature estimators behind the `Estimator` contract: `raw` (geometric inversion), `kf` (a
linear Kalman filter per segment) and `ukf` (an unscented Kalman filter on the whole arm).

Models (PHYSICS.md sections 2, 3, 5), nothing tuned by hand:

- Process: each segment bends as `I theta'' + d theta' + k theta = G_a (p_a - p_b) + w`, state
  (theta, omega), driven by the pressures of each cycle's DriveReading held constant until the
  next SYNC (ZOH) and discretised exactly (matrix exponential; Van Loan for the noise).
  The unmodelled torque w is white with the spectral density of a torque that is constant over
  one control period T with standard deviation `unmodelled_torque_std` (q = sigma^2 T): the
  pressure quantisation of the DriveStatus frame (10 Pa per channel, uniform, so
  G_a 10 Pa / sqrt(6) for the difference) and the table's Coulomb friction mu m g L / 2
  (mu = 0.3, m = 20 I / L^2 from the PCC bend inertia I = m L^2 / 20), added in quadrature.
- Measurement: marker positions with isotropic noise sigma^2 = noise^2 + q_m^2 / 12, the camera's
  noise plus the 20 um quantisation of the CameraMarker frame. `kf` measures one segment's
  curvature by the chord-angle inverse; `ukf` measures the visible markers themselves.
- Outliers: a Mahalanobis gate at the chi-square 0.999 quantile (per segment measurement, 1 dof,
  in `kf`; per marker, 2 dof, in `ukf`): a good measurement is rejected one time in a thousand.
- Latency: a picture is fused at its exposure time. The filters keep a short history of nodes
  (time, x, P, input held from that time); a frame is fused by predicting from the last node at
  or before its exposure, inserting a node there, and re-predicting every later node to the
  present with the inputs recorded since. Without compensation the picture counts as taken at
  the SYNC time.

Invariant: an estimate depends only on the sequence of `update` calls (bit-identical reruns).
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints
from scipy.linalg import expm
from scipy.stats import chi2

from controllers import cukf
from controllers.estimation import (
    BendModel,
    CameraNoise,
    DriveReading,
    Estimate,
    Estimator,
    MarkerFrame,
)
from controllers.kinematics import curvatures_from_markers

GATE_PROBABILITY = 0.999  # chi-square quantile of the outlier gate
# consecutive gated measurements of a segment after which the filter re-acquires it: outliers
# come one at a time (0.1 % of markers), a model that has lost the arm is gated every picture
REACQUIRE = 5
PRESSURE_QUANTUM = 10.0  # [Pa] DriveStatus p_a, p_b scale (softhil.dbc)
MARKER_QUANTUM = 2e-5  # [m] CameraMarker x, y scale (softhil.dbc)
TABLE_FRICTION = 0.3  # Coulomb coefficient of an elastomer on the table (PHYSICS.md section 2)
GRAVITY = 9.81  # [m/s^2]
NAMES = ("raw", "kf", "ukf")


def unmodelled_torque_std(bend: BendModel) -> float:
    """Standard deviation of the torque the bend model leaves out [N m]: pressure quantisation
    (G_a 10 Pa / sqrt 6) and table friction (mu m g L / 2, m = 20 I / L^2), in quadrature."""
    quantisation = bend.G_a * PRESSURE_QUANTUM / math.sqrt(6.0)
    mass = 20.0 * bend.inertia / bend.length**2
    friction = TABLE_FRICTION * mass * GRAVITY * bend.length / 2.0
    return math.hypot(quantisation, friction)


def marker_std(camera: CameraNoise) -> float:
    """Per-axis marker position standard deviation [m]: camera noise and bus quantisation."""
    return math.sqrt(camera.noise**2 + MARKER_QUANTUM**2 / 12.0)


class BendDiscretiser:
    """Exact discretisation of one segment's bend over a step dt, cached by dt.

    Parameters
    ----------
    bend
        The segment's model.
    torque_psd
        Spectral density of the unmodelled torque [N^2 m^2 s].
    """

    def __init__(self, bend: BendModel, torque_psd: float) -> None:
        self.A = np.array([[0.0, 1.0], [-bend.k_bend / bend.inertia, -bend.d_bend / bend.inertia]])
        self.B = np.array([0.0, bend.G_a / bend.inertia])
        noise_input = np.array([0.0, 1.0 / bend.inertia])
        self.Qc = torque_psd * np.outer(noise_input, noise_input)
        self._cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def __call__(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """F (2, 2), G (2,) [input per Pa] and Q (2, 2) for a step of dt [s]."""
        key = round(dt * 1e9)  # whole nanoseconds: float dt from subtraction hits the cache
        if key not in self._cache:
            step = key * 1e-9
            augmented = np.zeros((3, 3))
            augmented[:2, :2] = self.A
            augmented[:2, 2] = self.B
            transition = expm(augmented * step)
            F, G = transition[:2, :2], transition[:2, 2]
            # Van Loan: Q = F * integral of e^{-As} Qc e^{-A's} ds over the step
            van_loan = np.zeros((4, 4))
            van_loan[:2, :2] = -self.A
            van_loan[:2, 2:] = self.Qc
            van_loan[2:, 2:] = self.A.T
            block = expm(van_loan * step)
            Q = block[2:, 2:].T @ block[:2, 2:]
            self._cache[key] = (F, G, 0.5 * (Q + Q.T))
        return self._cache[key]


def _pressure_inputs(
    drives: Mapping[int, DriveReading], previous: np.ndarray | None, bends: Sequence[BendModel]
) -> np.ndarray:
    """h(p_a) - h(p_b) per segment [Pa] (the torque per G_a, `BendModel.effective_pressure`)
    from drives 1..N; a missing drive keeps its last value."""
    u = [0.0] * len(bends) if previous is None else previous.tolist()
    for n, bend in enumerate(bends, start=1):
        reading = drives.get(n)
        if reading is not None:
            u[n - 1] = bend.effective_pressure(reading.p_a) - bend.effective_pressure(reading.p_b)
    return np.array(u, dtype=float)


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


@dataclass
class _Node:
    """A point of the filter's history: the estimate at `time` and the input held from it."""

    time: float
    x: np.ndarray  # _PENDING: not yet predicted (`_LatencyFilter._settle`)
    P: np.ndarray
    u: np.ndarray


_PENDING = np.empty(0)


class _LatencyFilter:
    """History, latency compensation and the update cycle shared by `kf` and `ukf`; subclasses
    supply the prediction, the correction and the read-out of the state."""

    name = "filter"

    def __init__(
        self,
        bends: Sequence[BendModel],
        base: tuple[float, float, float],
        camera: CameraNoise,
        control_period: float,
        latency_compensation: bool,
        torque_std: float | None,
    ) -> None:
        self.bends = list(bends)
        self.lengths = np.array([b.length for b in bends])
        self.base = base
        self.segments = len(bends)
        self.sigma = marker_std(camera)
        self.latency_compensation = latency_compensation
        self.discretisers = [
            BendDiscretiser(
                b,
                (unmodelled_torque_std(b) if torque_std is None else torque_std) ** 2
                * control_period,
            )
            for b in bends
        ]
        # long enough for a frame to arrive: its latency, a frame period and a few SYNCs
        self.horizon = camera.latency + 1.0 / camera.rate + 4.0 * control_period
        self._nodes: list[_Node] = []
        self._u: np.ndarray | None = None
        self.stale = 0  # frames older than the history, not fused
        self.innovation: np.ndarray | None = None
        self.innovation_covariance: np.ndarray | None = None

    # subclass hooks -------------------------------------------------------------------------
    def _initial(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _predict(
        self, x: np.ndarray, P: np.ndarray, u: np.ndarray, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _correct(
        self, x: np.ndarray, P: np.ndarray, points: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, int, int]:
        raise NotImplementedError

    def _read(self, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """theta, omega, theta variance, each shape (N,)."""
        raise NotImplementedError

    def _initial_variances(self) -> tuple[np.ndarray, np.ndarray]:
        """Prior variances of theta [rad^2] and omega [rad^2/s^2]: the mechanical limit, and the
        limit over the bend's time constant."""
        theta_max = np.array([b.theta_max for b in self.bends])
        tau = np.array([b.d_bend / b.k_bend for b in self.bends])
        return theta_max**2, (theta_max / tau) ** 2

    # the cycle ------------------------------------------------------------------------------
    def update(
        self, t: float, drives: Mapping[int, DriveReading], frames: Sequence[MarkerFrame]
    ) -> Estimate:
        self._u = _pressure_inputs(drives, self._u, self.bends)
        if not self._nodes:
            x, P = self._initial()
            self._nodes.append(_Node(t, x, P, self._u))
        else:
            # predicted when first needed (`_settle`): a picture exposed before t, the usual
            # case with latency, predicts it again from the corrected history anyway
            self._nodes.append(_Node(t, _PENDING, _PENDING, self._u))
        gated = measured = 0
        for frame in frames:
            exposure = min(frame.exposure_time, t) if self.latency_compensation else t
            g, m = self._fuse(exposure, frame.points[:, :2])
            gated += g
            measured += m
        self._nodes = [n for n in self._nodes[:-1] if n.time >= t - self.horizon] + [
            self._nodes[-1]
        ]
        last = self._settle(len(self._nodes) - 1)
        theta, omega, variance = self._read(last.x, last.P)
        return Estimate(
            theta / self.lengths,
            omega / self.lengths,
            np.sqrt(np.maximum(variance, 0.0)) / self.lengths,
            gated,
            measured,
        )

    def _settle(self, j: int) -> _Node:
        """History node j, its prediction from node j - 1 made if it is still pending."""
        node = self._nodes[j]
        if node.x is _PENDING:
            previous = self._nodes[j - 1]
            node.x, node.P = self._predict(
                previous.x, previous.P, previous.u, node.time - previous.time
            )
        return node

    def _fuse(self, exposure: float, points: np.ndarray) -> tuple[int, int]:
        """Fuse one picture at `exposure` and carry the history to the present."""
        tolerance = 1e-9
        j = len(self._nodes) - 1
        while j >= 0 and self._nodes[j].time > exposure + tolerance:
            j -= 1
        if j < 0:
            self.stale += 1
            return 0, 0
        node = self._settle(j)
        x, P = self._predict(node.x, node.P, node.u, exposure - node.time)
        x, P, gated, measured = self._correct(x, P, points)
        if exposure - node.time <= tolerance:
            node.x, node.P = x, P
        else:
            j += 1
            self._nodes.insert(j, _Node(exposure, x, P, node.u))
        for k in range(j + 1, len(self._nodes)):
            previous, current = self._nodes[k - 1], self._nodes[k]
            current.x, current.P = self._predict(
                previous.x, previous.P, previous.u, current.time - previous.time
            )
        return gated, measured


class SegmentKalmanEstimator(_LatencyFilter):
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
        x = _einsum("nij,nj->ni", F, x) + G * u[:, np.newaxis]
        P = _einsum("nij,njk,nlk->nil", F, P, F) + Q
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


class ArmUnscentedEstimator(_LatencyFilter):
    """An unscented Kalman filter (filterpy, Merwe scaled sigma points: alpha 1, beta 2, kappa 0:
    every covariance weight positive, so P stays positive definite for any number of segments;
    a small alpha gives the central point a weight of about -1/alpha^2, which made P indefinite
    on six segments) over the whole arm, state (theta_1..N, omega_1..N), measuring the visible
    segment-end markers through the PCC forward kinematics; any subset of markers updates what
    it can. The base marker carries no information on the state (the base is fixed) and is not
    used. The dynamics are linear, so the prediction is the exact linear one; the unscented
    transform is used for the measurement (filterpy's sigma points and weights; its update
    inlined over the sigma points already carried through the kinematics for the gate, for
    speed). Each marker is gated on its own 2 x 2 block of the innovation covariance, and the
    accepted markers update together."""

    name = "ukf"

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
        n = self.segments
        self.points_fn = MerweScaledSigmaPoints(
            2 * n, alpha=1.0, beta=2.0, kappa=0.0, sqrt_method=_robust_sqrt
        )
        self.gate = float(chi2.ppf(GATE_PROBABILITY, 2))
        # (lambda + n) of the Merwe points: the scale of P whose square root spreads the sigmas
        lambda_ = self.points_fn.alpha**2 * (2 * n + self.points_fn.kappa) - 2 * n
        self._spread = lambda_ + 2 * n  # as filterpy computes it
        self._arm_cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        # constants of the update, built once: the covariance weights as a diagonal matrix and
        # the measurement noise sigma^2 I by measurement size
        self._Wc_diagonal = np.diag(self.points_fn.Wc)
        self._noise: dict[int, np.ndarray] = {}
        self._c = _CUkf(self) if cukf.load() is not None else None

    def _initial(self) -> tuple[np.ndarray, np.ndarray]:
        var_theta, var_omega = self._initial_variances()
        return np.zeros(2 * self.segments), np.diag(np.concatenate([var_theta, var_omega]))

    def _arm_matrices(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """F (2N, 2N), G (2N, N) and Q (2N, 2N) of the whole arm over dt [s], cached by dt."""
        key = round(dt * 1e9)
        if key not in self._arm_cache:
            n = self.segments
            F, Q, G = np.zeros((2 * n, 2 * n)), np.zeros((2 * n, 2 * n)), np.zeros((2 * n, n))
            for i, discretise in enumerate(self.discretisers):
                Fi, Gi, Qi = discretise(dt)
                index = np.ix_([i, n + i], [i, n + i])
                F[index], Q[index] = Fi, Qi
                G[[i, n + i], i] = Gi
            self._arm_cache[key] = (F, G, Q)
        return self._arm_cache[key]

    def _predict(
        self, x: np.ndarray, P: np.ndarray, u: np.ndarray, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        if self._c is not None:
            return self._c.predict(x, P, u, dt)
        return self._predict_numpy(x, P, u, dt)

    def _predict_numpy(
        self, x: np.ndarray, P: np.ndarray, u: np.ndarray, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        F, G, Q = self._arm_matrices(dt)
        P = F @ P @ F.T + Q
        return F @ x + G @ u, 0.5 * (P + P.T)

    def _segment_ends(self, states: np.ndarray) -> np.ndarray:
        """Segment-end marker positions for states shape (S, 2N): shape (S, N, 2) [m].

        The PCC chain of `controllers.kinematics.forward` in its chord form (chord L sinc(theta/2)
        along the start heading plus theta/2), vectorised over the sigma points."""
        theta = states[:, : self.segments]
        start = self.base[2] + theta.cumsum(axis=1) - theta
        half = 0.5 * theta
        direction = start + half
        straight = half == 0.0
        safe = np.where(straight, 1.0, half)
        chord = self.lengths * np.where(straight, 1.0, np.sin(safe) / safe)
        ends = np.empty((*theta.shape, 2))
        ends[..., 0] = self.base[0] + (chord * np.cos(direction)).cumsum(axis=1)
        ends[..., 1] = self.base[1] + (chord * np.sin(direction)).cumsum(axis=1)
        return ends

    def _markers(self, state: np.ndarray, which: np.ndarray) -> np.ndarray:
        """Positions of the markers `which` (indices 1..N) for one state, flattened [m]."""
        return self._segment_ends(state[np.newaxis])[0, which - 1].ravel()

    def _sigma_points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """filterpy's `MerweScaledSigmaPoints.sigma_points` without its loop over the state:
        the same square root and the same sums (x - (-U[k]) is x + U[k] exactly)."""
        n = 2 * self.segments
        U = _robust_sqrt(self._spread * P)
        sigmas = np.empty((2 * n + 1, n))
        sigmas[0] = x
        sigmas[1 : n + 1] = x + U
        sigmas[n + 1 :] = x - U
        return sigmas

    def _correct(
        self, x: np.ndarray, P: np.ndarray, points: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, int, int]:
        if self._c is not None:
            corrected = self._c.correct(x, P, points)
            if corrected is not None:
                return corrected
        return self._correct_numpy(x, P, points)

    def _correct_numpy(
        self, x: np.ndarray, P: np.ndarray, points: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, int, int]:
        seen = ~np.isnan(points).any(axis=1)
        visible = seen[1:].nonzero()[0] + 1
        if visible.size == 0:
            return x, P, 0, 0
        Wm, Wc = self.points_fn.Wm, self.points_fn.Wc
        sigmas = self._sigma_points(x, P)
        predicted = self._segment_ends(sigmas)[:, visible - 1].reshape(len(sigmas), -1)
        zp = Wm @ predicted
        # each marker gated on its own 2 x 2 block of the innovation covariance, all markers at
        # once: the blocks' entries and the Mahalanobis distance in closed form
        d = (predicted - zp).reshape(len(sigmas), visible.size, 2)
        weighted = d * Wc[:, np.newaxis, np.newaxis]
        s00 = _einsum("sk,sk->k", weighted[..., 0], d[..., 0]) + self.sigma**2
        s01 = _einsum("sk,sk->k", weighted[..., 0], d[..., 1])
        s11 = _einsum("sk,sk->k", weighted[..., 1], d[..., 1]) + self.sigma**2
        r = points[visible] - zp.reshape(visible.size, 2)
        distance = (s11 * r[:, 0] ** 2 - 2.0 * s01 * r[:, 0] * r[:, 1] + s00 * r[:, 1] ** 2) / (
            s00 * s11 - s01 * s01
        )
        keep = distance <= self.gate
        gated = int(visible.size - np.count_nonzero(keep))
        if not keep.any():
            return x, P, gated, 0
        which = visible[keep]
        # filterpy's UnscentedKalmanFilter.update, inlined on the sigma points already carried
        # through the kinematics for the gate: the unscented transform as filterpy computes it,
        # its cross variance as one product instead of a sum of outer products
        sigmas_h = predicted[:, keep.repeat(2)]
        zp = np.dot(Wm, sigmas_h)
        dz = sigmas_h - zp[np.newaxis, :]
        noise = self._noise.get(which.size)
        if noise is None:
            noise = self._noise[which.size] = self.sigma**2 * np.eye(2 * which.size)
        S = np.dot(dz.T, np.dot(self._Wc_diagonal, dz)) + noise
        Pxz = ((sigmas - x) * Wc[:, np.newaxis]).T @ dz
        K = Pxz @ _inverse(S)
        y = points[which].ravel() - zp
        x = x + K @ y
        P = P - K @ (S @ K.T)
        self.innovation, self.innovation_covariance = y, S
        return x, 0.5 * (P + P.T), gated, which.size

    def _read(self, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = self.segments
        return x[:n], x[n:], P.diagonal()[:n]


class _CUkf:
    """An ArmUnscentedEstimator's prediction and correction through `controllers.cukf`: the
    C code works on buffers made once here (inputs copied in, outputs copied out)."""

    def __init__(self, est: ArmUnscentedEstimator) -> None:
        library = cukf.load()
        assert library is not None
        self._predict_c, self._correct_c = library.softhil_ukf_predict, library.softhil_ukf_correct
        self.est = est
        N = est.segments
        n = 2 * N

        def buffer(*shape: int) -> np.ndarray:
            return np.zeros(shape)

        self.lengths = np.ascontiguousarray(est.lengths, dtype=float)
        self.Wm = np.ascontiguousarray(est.points_fn.Wm, dtype=float)
        self.Wc = np.ascontiguousarray(est.points_fn.Wc, dtype=float)
        self.x, self.P, self.points, self.u = buffer(n), buffer(n, n), buffer(N + 1, 2), buffer(N)
        self.x_out, self.P_out = buffer(n), buffer(n, n)
        self.y, self.S, self.work = buffer(2 * N), buffer(4 * N * N), buffer(cukf.work_size(N))
        ws = self.ws = cukf.Workspace()
        ws.segments, ws.spread = N, est._spread
        ws.noise, ws.gate = est.sigma**2, est.gate
        ws.base[:] = [float(b) for b in est.base]
        for name in ("lengths", "Wm", "Wc", "x", "P", "points", "u", "x_out", "P_out", "y", "S"):
            setattr(ws, name, _pointer(getattr(self, name)))
        ws.work = _pointer(self.work)
        self.ref = ctypes.byref(ws)
        # the arm matrices' addresses by dt (the estimator's cache keeps the arrays alive)
        self._matrices: dict[int, tuple[Any, Any, Any]] = {}

    def predict(
        self, x: np.ndarray, P: np.ndarray, u: np.ndarray, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        key = round(dt * 1e9)  # as `_arm_matrices` keys its cache, which keeps the arrays
        pointers = self._matrices.get(key)
        if pointers is None:
            F, G, Q = self.est._arm_matrices(dt)
            pointers = self._matrices[key] = (_pointer(F), _pointer(G), _pointer(Q))
        ws = self.ws
        ws.F, ws.G, ws.Q = pointers
        self.x[:], self.P[:], self.u[:] = x, P, u
        self._predict_c(self.ref)
        return self.x_out.copy(), self.P_out.copy()

    def correct(
        self, x: np.ndarray, P: np.ndarray, points: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, int, int] | None:
        """The correction, or None where the numpy path must decide (no Cholesky factor)."""
        self.x[:], self.P[:], self.points[:] = x, P, points
        if self._correct_c(self.ref) != 0:
            return None
        ws = self.ws
        if ws.measured == 0:
            return x, P, ws.gated, 0
        m = 2 * ws.measured
        self.est.innovation = self.y[:m].copy()
        self.est.innovation_covariance = self.S[: m * m].reshape(m, m).copy()
        return self.x_out.copy(), self.P_out.copy(), ws.gated, ws.measured


def _pointer(array: np.ndarray) -> Any:
    assert array.dtype == np.float64 and array.flags.c_contiguous
    return array.ctypes.data_as(ctypes.POINTER(ctypes.c_double))


_INV: Any = None
_CHOLESKY: Any = None
_einsum: Any = np.einsum  # a numpy that keeps c_einsum elsewhere: the public function
with contextlib.suppress(ImportError):  # what np.einsum calls when not asked to optimise
    from numpy._core.multiarray import c_einsum as _einsum
try:  # the kernels behind np.linalg.inv and np.linalg.cholesky: the same LAPACK calls
    from numpy.linalg import _umath_linalg

    _INV, _CHOLESKY = _umath_linalg.inv, _umath_linalg.cholesky_lo
except (ImportError, AttributeError):  # a numpy that moved them: the public functions
    pass


def _inverse(S: np.ndarray) -> np.ndarray:
    """np.linalg.inv of a real matrix, bit for bit, without its checks and wrapping (7 us
    instead of 16 on the UKF's 12 x 12); a singular matrix raises np.linalg.LinAlgError."""
    if _INV is not None:
        try:
            with np.errstate(invalid="raise", over="ignore", divide="ignore", under="ignore"):
                return _INV(S, signature="d->d")  # type: ignore[no-any-return]
        except FloatingPointError:
            pass  # singular: np.linalg.inv raises what it raises
    return np.linalg.inv(S)


def _robust_sqrt(P: np.ndarray) -> np.ndarray:
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


def make_estimator(
    name: str,
    bends: Sequence[BendModel],
    base: tuple[float, float, float],
    camera: CameraNoise,
    control_period: float,
    latency_compensation: bool = True,
    torque_std: float | None = None,
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
    """
    if name == "raw":
        return RawEstimator(bends, base)
    if name == "kf":
        return SegmentKalmanEstimator(
            bends, base, camera, control_period, latency_compensation, torque_std
        )
    if name == "ukf":
        return ArmUnscentedEstimator(
            bends, base, camera, control_period, latency_compensation, torque_std
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


class ObjectTracker:
    """Kalman filters of the objects' centres from their camera markers: per object a
    random-walk position (process noise `drift` [m/sqrt(s)]: an object stays put unless the arm
    moves it) measured with the camera's marker noise, started at its first sighting; a marker
    further than GATE standard deviations from the prediction is an outlier and is dropped,
    unless REACQUIRE pictures in a row say so: then the object has moved (the arm carries it)
    and the filter restarts at the marker."""

    GATE = 5.0  # Mahalanobis distance beyond which a marker is an outlier

    def __init__(self, objects: int, camera: CameraNoise, drift: float = 2e-3) -> None:
        self.x = np.full((objects, 2), np.nan)
        self.P = np.full(objects, np.inf)  # isotropic variance [m^2]
        self.R = marker_std(camera) ** 2
        self.q = drift**2
        self.time = np.full(objects, np.nan)
        self.rejected = np.zeros(objects, int)  # consecutive gated markers

    def update(self, points: np.ndarray, exposure: float) -> int:
        """Fuse one picture's object markers (shape (objects, 2), NaN where unseen); returns the
        number of outliers rejected."""
        gated = 0
        for o, z in enumerate(points):
            if np.isnan(z).any():
                continue
            if np.isnan(self.time[o]) or self.rejected[o] + 1 >= REACQUIRE:
                self.x[o], self.P[o], self.time[o] = z, self.R, exposure
                self.rejected[o] = 0
                continue
            P = self.P[o] + self.q * max(exposure - self.time[o], 0.0)
            S = P + self.R
            innovation = z - self.x[o]
            if float(innovation @ innovation) / S > self.GATE**2:
                gated += 1
                self.rejected[o] += 1
                continue
            self.rejected[o] = 0
            gain = P / S
            self.x[o] = self.x[o] + gain * innovation
            self.P[o], self.time[o] = (1.0 - gain) * P, exposure
        return gated


class WithObjects:
    """An arm estimator plus an ObjectTracker: the arm's markers (the first `markers` of each
    picture) go to the arm's estimator, the rest to the tracker; the estimate carries both."""

    def __init__(self, arm: Estimator, markers: int, tracker: ObjectTracker) -> None:
        self.arm, self.markers, self.tracker = arm, markers, tracker
        self.name = arm.name

    def update(
        self, t: float, drives: Mapping[int, DriveReading], frames: Sequence[MarkerFrame]
    ) -> Estimate:
        gated = 0
        for frame in frames:
            gated += self.tracker.update(frame.points[self.markers :], frame.exposure_time)
        arm_frames = [
            MarkerFrame(exposure_time=f.exposure_time, points=f.points[: self.markers])
            for f in frames
        ]
        estimate = self.arm.update(t, drives, arm_frames)
        return dataclasses.replace(
            estimate, objects=self.tracker.x.copy(), gated=estimate.gated + gated
        )
