"""The spatial arm's bend estimate from the camera's 3-D markers and the drives' pistons.

Measurement. `ik` (the published Algorithm 2): each picture's endplate markers in the base frame
give, segment by segment from the base, the segment's bends by single-segment inverse kinematics
in the frame the previous segment's tip defines (`marker_ik.bends_from_markers`); a segment
whose marker or whose base's is missing keeps its last value. `kf`: the markers themselves are
the measurement, an extended step of the Kalman filter through the markers' Jacobian
(`markers.Markers`): every marker seen counts, the base's errors do not carry into
the tip's bends as in the walk, and a missing marker only removes its own three rows.

Filter (`kf`): filterpy's Kalman filter on the bends and their rates, whose prediction knows
gravity and the arm's inertia: between pictures the bends move by the arm's dynamics linearised
about the static equilibrium the measured pistons hold under gravity (`dynamics`: M e'' + D e'
+ H e = 0, e = q - q_eq, exactly discretised). The equilibrium is linearised in the pistons
(one Newton step of the static balance from the estimate, and its sensitivity dq/dx,
`_relinearise`), and M, H with it, every RELINEARISE seconds or
beyond DRIFT of piston travel: a full solve costs tens of milliseconds, the linearisation a few,
the prediction from it microseconds.

Each marker coordinate has the camera's noise; a marker whose innovation is beyond GATE_CHI2
(Mahalanobis, 3 dof) is rejected as an outlier (the camera's outliers move a marker by
centimetres).

The object (task `object`): its marker's positions averaged over the pictures that hold it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter

from controllers.estimation import DriveReading, MarkerFrame
from robots.spatial_arm.controller import dynamics, marker_ik, statics
from robots.spatial_arm.controller.config import SpatialConfig
from robots.spatial_arm.controller.markers import Markers
from robots.spatial_arm.controller.model import ArmModel

PROCESS_ACCELERATION = 2.0  # [rad/s^2 per square-root hertz] what the linearisation misses
RELINEARISE = 1.0  # [s] between linearisations of the equilibrium the pistons hold
DRIFT = 0.01  # [m] of piston travel beyond which it is linearised again sooner
GATE_CHI2 = 30.0  # Mahalanobis gate of a marker's innovation (3 dof: p < 1e-6)


@dataclass(frozen=True)
class SpatialEstimate:
    """The bends (theta_x_1, theta_y_1, ...) [rad], their standard deviations, the tip and
    every endplate in the base frame [m], the object's centre (NaN: not seen yet) and the
    equilibrium the pistons hold."""

    q: np.ndarray
    q_rate: np.ndarray
    q_std: np.ndarray
    markers: np.ndarray  # (N + 1, 3)
    object: np.ndarray  # (3,)
    object_frames: int
    equilibrium: np.ndarray
    measured: int = 0
    gated: int = 0

    @property
    def tip(self) -> np.ndarray:
        return self.markers[-1]


class SpatialEstimator:
    def __init__(self, config: SpatialConfig, model: ArmModel) -> None:
        self.config = config
        self.model = model
        self.n_q = model.n_q
        self.segments = config.segments
        start = np.asarray(config.start, dtype=float)
        self.q_eq = start.copy()
        self.pistons = np.full(self.n_q, model.x_seal)
        self.markers = Markers(model)
        self.q_lin, self.x_lin = start.copy(), self.pistons.copy()
        self.S = np.zeros((self.n_q, self.n_q))
        self.t_lin = -math.inf
        n = self.n_q
        # the state: the bends and their rates
        self.filter = KalmanFilter(dim_x=2 * n, dim_z=n, dim_u=2 * n)
        self.filter.x = np.concatenate([start, np.zeros(n)])
        self.filter.P = np.diag(np.r_[np.full(n, 1e-4), np.full(n, 1e-2)])
        self.D = dynamics.damping_matrix(model)
        self.M = dynamics.mass_matrix(model, start)
        self.H = statics.stiffness(model, start, self.pistons)
        self._transitions: dict[float, np.ndarray] = {}
        self.r_marker = config.camera_noise**2
        self.last_time = 0.0
        self.object_sum = np.zeros(3)
        self.object_frames = 0
        self.measured = 0
        self.gated = 0

    # ------------------------------------------------------------------ prediction

    def _equilibrium(self, drives: Mapping[int, DriveReading], t: float) -> np.ndarray:
        """The equilibrium the measured pistons hold, from the linearisation about the last
        one (re-made every RELINEARISE seconds or beyond DRIFT of piston travel)."""
        for n, reading in drives.items():
            if 1 <= n <= self.n_q:
                self.pistons[n - 1] = reading.piston_position
        travel = float(np.max(np.abs(self.pistons - self.x_lin)))
        if t - self.t_lin >= RELINEARISE or travel > DRIFT:
            self._relinearise(t)
        self.q_eq = self.q_lin + self.S @ (self.pistons - self.x_lin)
        return self.q_eq

    def _relinearise(self, t: float) -> None:
        """One Newton step from the estimate to the equilibrium at the pistons, and its
        sensitivity to them: dq/dx = H^-1 diag(dtau/dx), H the static stiffness (the potential's
        Hessian: bending, gravity, gas)."""
        q, x = np.array(self.filter.x[: self.n_q], dtype=float), self.pistons.copy()
        H = statics.stiffness(self.model, q, x)
        r = statics.residual(self.model, q, x)
        d_x = statics.gas_torque(self.model, q, x).d_x
        try:
            step = np.linalg.solve(H, r)
            S = np.linalg.solve(H, np.diag(d_x))
        except np.linalg.LinAlgError:  # not a stable rest here: keep the last linearisation
            return
        self.q_lin, self.x_lin, self.S, self.t_lin = q - step, x, S, t
        self.M, self.H = dynamics.mass_matrix(self.model, q), H
        self._transitions.clear()

    def _transition(self, dt: float) -> np.ndarray:
        key = round(dt, 9)
        found = self._transitions.get(key)
        if found is None:
            if len(self._transitions) > 16:
                self._transitions.clear()
            found = dynamics.transition(self.M, self.H, self.D, dt)
            self._transitions[key] = found
        return found

    def _predict(self, t: float) -> None:
        """The linearised dynamics about the equilibrium the pistons hold: (e, e') evolves by
        exp(A dt), e = q - q_eq; white acceleration noise PROCESS_ACCELERATION (what the
        linearisation misses)."""
        dt = t - self.last_time
        if dt <= 0.0:
            return
        n = self.n_q
        F = self._transition(dt)
        f = self.filter
        f.F = F
        f.B = np.eye(2 * n) - F
        q_rate = PROCESS_ACCELERATION**2
        f.Q = np.diag(np.r_[np.full(n, q_rate * dt**3 / 3.0), np.full(n, q_rate * dt)])
        f.predict(u=np.concatenate([self.q_eq, np.zeros(n)]))
        self.last_time = t

    # ------------------------------------------------------------------ measurement

    def _arm_markers(self, frame: MarkerFrame) -> np.ndarray:
        """The picture's endplate markers (N, 3), NaN rows where it does not hold them."""
        return np.asarray(frame.points, dtype=float)[1 : self.segments + 1]

    def _update(self, frame: MarkerFrame) -> None:
        seen_points = self._arm_markers(frame)
        seen = ~np.isnan(seen_points).any(axis=1)
        if not seen.any():
            return
        if self.config.estimator == "ik":
            arm = np.vstack([np.zeros(3), seen_points])
            q = np.asarray(marker_ik.bends_from_markers(self.model, arm), dtype=float)
            valid = ~np.isnan(q)
            self.filter.x[: self.n_q] = np.where(valid, q, self.filter.x[: self.n_q])
            self.measured += int(seen.sum())
            return
        f = self.filter
        predicted, J = self.markers(f.x[: self.n_q])
        H_all, h_all = J[1:], predicted[1:]  # (N, 3, n_q), (N, 3)
        # gate each marker on its innovation against its predicted spread (3 dof)
        P_q = f.P[: self.n_q, : self.n_q]
        keep = []
        for i in np.flatnonzero(seen):
            S = H_all[i] @ P_q @ H_all[i].T + self.r_marker * np.eye(3)
            innovation = seen_points[i] - h_all[i]
            if float(innovation @ np.linalg.solve(S, innovation)) <= GATE_CHI2:
                keep.append(i)
            else:
                self.gated += 1
        if not keep:
            return
        H = np.zeros((3 * len(keep), 2 * self.n_q))
        H[:, : self.n_q] = H_all[keep].reshape(-1, self.n_q)
        z = seen_points[keep].ravel()
        # the extended filter's step through the linear one: z - h(x) + H x against H
        z_lin = z - h_all[keep].ravel() + H @ f.x
        f.update(z_lin, R=np.eye(len(z)) * self.r_marker, H=H)
        self.measured += len(keep)

    def _object(self, frame: MarkerFrame) -> None:
        index = self.segments + 1
        if len(frame.points) > index and not np.isnan(frame.points[index]).any():
            self.object_sum += frame.points[index]
            self.object_frames += 1

    # ------------------------------------------------------------------ each cycle

    def update(
        self, t: float, drives: Mapping[int, DriveReading], frames: Sequence[MarkerFrame]
    ) -> SpatialEstimate:
        self.measured = self.gated = 0
        self._equilibrium(drives, t)
        for frame in sorted(frames, key=lambda f: f.exposure_time):
            self._predict(frame.exposure_time)
            self._update(frame)
            self._object(frame)
        self._predict(t)
        q = np.array(self.filter.x[: self.n_q], dtype=float)
        obj = self.object_sum / self.object_frames if self.object_frames else np.full(3, math.nan)
        return SpatialEstimate(
            q=q,
            q_rate=np.array(self.filter.x[self.n_q :], dtype=float),
            q_std=np.sqrt(np.maximum(np.diag(self.filter.P)[: self.n_q], 0.0)),
            markers=self.markers(q)[0],
            object=obj,
            object_frames=self.object_frames,
            equilibrium=self.q_eq.copy(),
            measured=self.measured,
            gated=self.gated,
        )
