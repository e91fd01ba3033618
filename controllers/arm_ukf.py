"""`ukf`: an unscented Kalman filter on the whole arm (controllers.bend_filter: the models, the
outlier gate and the latency compensation it shares with `kf`), its prediction and correction in
C where the compiler is there (controllers.cukf), in numpy otherwise.

Invariant: an estimate depends only on the sequence of `update` calls (bit-identical reruns).
"""

from __future__ import annotations

import ctypes
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints
from scipy.stats import chi2

from controllers import cukf, kinematics
from controllers.bend_filter import (
    GATE_PROBABILITY,
    CoupledBends,
    LatencyFilter,
    unmodelled_torque_std,
)
from controllers.estimation import BendModel, CameraNoise, DriveReading, Estimate, MarkerFrame
from controllers.fast_linalg import einsum, inverse, robust_sqrt

# relative change of the mass matrix (of its largest entry) at which `ukf` rediscretises a
# multibody arm's prediction
MASS_MATRIX_CHANGE = 0.02


class ArmUnscentedEstimator(LatencyFilter):
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
        masses: Sequence[float] | None = None,
    ) -> None:
        super().__init__(bends, base, camera, control_period, latency_compensation, torque_std)
        n = self.segments
        # a multibody arm: its bends predicted coupled by the mass matrix at the estimated
        # configuration (`_schedule`), else each alone
        self.masses = None if masses is None else np.asarray(masses, dtype=float)
        self.torque_psd = [
            (unmodelled_torque_std(b) if torque_std is None else torque_std) ** 2 * control_period
            for b in self.bends
        ]
        self.coupled: CoupledBends | None = None
        self._scheduled: np.ndarray | None = None  # the mass matrix `coupled` was made with
        self.points_fn = MerweScaledSigmaPoints(
            2 * n, alpha=1.0, beta=2.0, kappa=0.0, sqrt_method=robust_sqrt
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
        if self.masses is not None:
            self._schedule(np.zeros(n))  # the straight arm, the filter's prior

    def update(
        self, t: float, drives: Mapping[int, DriveReading], frames: Sequence[MarkerFrame]
    ) -> Estimate:
        estimate = super().update(t, drives, frames)
        if self.masses is not None:
            self._schedule(estimate.kappa * self.lengths)
        return estimate

    def _schedule(self, theta: np.ndarray) -> None:
        """The coupled prediction with the mass matrix at bend angles `theta`, made anew where it
        moved by more than MASS_MATRIX_CHANGE of its largest entry (curled, the six-segment
        arm's base carries a third of the straight arm's inertia)."""
        assert self.masses is not None
        M = kinematics.mass_matrix(theta / self.lengths, self.lengths, self.masses)
        if self._scheduled is not None:
            change = float(np.max(np.abs(M - self._scheduled)))
            if change <= MASS_MATRIX_CHANGE * float(np.max(np.abs(self._scheduled))):
                return
        self.coupled = CoupledBends(self.bends, M, self.torque_psd)
        self._scheduled = M
        self._arm_cache.clear()
        if self._c is not None:
            self._c.forget()

    def _initial(self) -> tuple[np.ndarray, np.ndarray]:
        var_theta, var_omega = self._initial_variances()
        return np.zeros(2 * self.segments), np.diag(np.concatenate([var_theta, var_omega]))

    def _arm_matrices(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """F (2N, 2N), G (2N, N) and Q (2N, 2N) of the whole arm over dt [s], cached by dt."""
        key = round(dt * 1e9)
        if key not in self._arm_cache and self.coupled is not None:
            self._arm_cache[key] = self.coupled(dt)
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
        U = robust_sqrt(self._spread * P)
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
        s00 = einsum("sk,sk->k", weighted[..., 0], d[..., 0]) + self.sigma**2
        s01 = einsum("sk,sk->k", weighted[..., 0], d[..., 1])
        s11 = einsum("sk,sk->k", weighted[..., 1], d[..., 1]) + self.sigma**2
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
        K = Pxz @ inverse(S)
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

    def forget(self) -> None:
        """Drop the arm matrices' addresses: the estimator made new ones."""
        self._matrices.clear()

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
