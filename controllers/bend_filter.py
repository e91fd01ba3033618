"""What the model-based curvature estimators (`kf`: controllers.segment_kf, `ukf`:
controllers.arm_ukf) share: each segment's bend model discretised with its noise, the pressure
inputs, and the history that fuses each picture at its exposure time (`LatencyFilter`).

Models (fmus/FeaSegment/model.c, controllers/kinematics.py, hil/vision.py), nothing tuned by
hand:

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

Invariant: a filter's estimate depends only on the sequence of `update` calls (bit-identical
reruns).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from controllers.estimation import (
    BendModel,
    CameraNoise,
    DriveReading,
    Estimate,
    MarkerFrame,
)

GATE_PROBABILITY = 0.999  # chi-square quantile of the outlier gate
# consecutive gated measurements of a segment after which the filter re-acquires it: outliers
# come one at a time (0.1 % of markers), a model that has lost the arm is gated every picture
REACQUIRE = 5
PRESSURE_QUANTUM = 10.0  # [Pa] DriveStatus p_a, p_b scale (softhil.dbc)
MARKER_QUANTUM = 2e-5  # [m] CameraMarker x, y scale (softhil.dbc)
TABLE_FRICTION = 0.3  # Coulomb, an elastomer on the table [estimate, fmus/Environment/model.c]
GRAVITY = 9.81  # [m/s^2]


def unmodelled_torque_std(bend: BendModel) -> float:
    """Standard deviation of the torque the bend model leaves out [N m]: pressure quantisation
    (G_a 10 Pa / sqrt 6) and table friction (mu m g L / 2, m the bend's mass, else 20 I / L^2),
    in quadrature."""
    quantisation = bend.G_a * PRESSURE_QUANTUM / math.sqrt(6.0)
    mass = bend.mass or 20.0 * bend.inertia / bend.length**2
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


class CoupledBends:
    """Exact discretisation of a multibody arm's bends over a step dt, cached by dt: state
    (theta_1..N, omega_1..N), `M theta'' + D theta' + K theta = G_a u + w` with the arm's mass
    matrix M (constant: the straight arm's), D, K and G_a diagonal from the bends, u the
    pressure inputs [Pa] and w each bend's unmodelled torque (white, spectral densities
    `torque_psd`, independent between the bends). The per-bend `BendDiscretiser` is its
    diagonal M without the coupling.
    """

    def __init__(
        self, bends: Sequence[BendModel], mass_matrix: np.ndarray, torque_psd: Sequence[float]
    ) -> None:
        n = len(bends)
        if mass_matrix.shape != (n, n):
            raise ValueError(f"mass_matrix: shape {mass_matrix.shape} for {n} bends")
        inverse = np.linalg.inv(mass_matrix)
        self.A = np.zeros((2 * n, 2 * n))
        self.A[:n, n:] = np.eye(n)
        self.A[n:, :n] = -inverse @ np.diag([b.k_bend for b in bends])
        self.A[n:, n:] = -inverse @ np.diag([b.d_bend for b in bends])
        self.B = np.zeros((2 * n, n))
        self.B[n:, :] = inverse @ np.diag([b.G_a for b in bends])
        noise_input = np.zeros((2 * n, n))
        noise_input[n:, :] = inverse
        self.Qc = noise_input @ np.diag(torque_psd) @ noise_input.T
        self.n = n

    def __call__(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """F (2N, 2N), G (2N, N) [per Pa] and Q (2N, 2N) for a step of dt [s]: Van Loan over a
        step h = dt / 2^k short against the arm's fastest mode (|A| h <= 1/2; over the whole
        step its exp(-A dt) would reach e^100 on the six-segment arm and cancel every digit),
        then doubled k times exactly (F_2h = F_h^2, G_2h = F_h G_h + G_h,
        Q_2h = F_h Q_h F_h' + Q_h)."""
        n2 = 2 * self.n
        step = round(dt * 1e9) * 1e-9
        reach = float(np.linalg.norm(self.A, 1)) * step  # |A| dt
        halvings = math.ceil(math.log2(2.0 * reach)) if reach > 0.5 else 0
        h = step / 2.0**halvings
        augmented = np.zeros((n2 + self.n, n2 + self.n))
        augmented[:n2, :n2] = self.A
        augmented[:n2, n2:] = self.B
        transition = expm(augmented * h)
        F, G = transition[:n2, :n2], transition[:n2, n2:]
        van_loan = np.zeros((2 * n2, 2 * n2))
        van_loan[:n2, :n2] = -self.A
        van_loan[:n2, n2:] = self.Qc
        van_loan[n2:, n2:] = self.A.T
        block = expm(van_loan * h)
        Q = block[n2:, n2:].T @ block[:n2, n2:]
        for _ in range(halvings):
            F, G, Q = F @ F, F @ G + G, F @ Q @ F.T + Q
        Q = 0.5 * (Q + Q.T)
        return tuple(np.ascontiguousarray(a) for a in (F, G, Q))  # type: ignore[return-value]


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


@dataclass
class _Node:
    """A point of the filter's history: the estimate at `time` and the input held from it."""

    time: float
    x: np.ndarray  # _PENDING: not yet predicted (`LatencyFilter._settle`)
    P: np.ndarray
    u: np.ndarray


_PENDING = np.empty(0)


class LatencyFilter:
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
