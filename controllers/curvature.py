"""Outer curvature loop: one PI per segment from curvature error to the
piston position setpoint, with its design from the segment's linearised physics.

Linearised at sealing (both sides at p_atm, mid-stroke, unbent), a segment's curvature answers
the piston position as a first-order lag: the gas law with compliance gives each side a
stiffness dp/dV = p_atm / (V_seal,i + p_atm C_a), the antagonistic pair a torque G_a (p_a - p_b),
and the bending equation (inertia negligible against damping, I/d ~ 1 ms for a lone segment;
not so in a multibody arm: `ArmGains`) a pole at (k + k_gas) / d. Hence
    kappa / x_piston = K / (tau s + 1),  K = S G_a A / (L (k + S G_a^2)),
    tau = d / (k + S G_a^2),  S = sum over both sides of p_atm / (V_seal,i + p_atm C_a).
The PI zero cancels the lag (Ki = Kp / tau) and Kp sets the crossover: Kp = wc tau / K.

Beyond the linearisation, `SegmentModel.equilibrium_curvature` solves the segment's nonlinear
static balance (isothermal gas in both sealed circuits, the vacuum collapse of the expanded side,
the channel compliance, the mechanical limit) exactly as the FeaSegment FMU's steady state, and
`reachable_curvature` evaluates it at the ends of the stroke: the curvature bounds of the arm's
task-space IK. Sign: the piston towards `stroke` compresses side a and bends positively.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from controllers import kinematics


def brentq(*args: object, **kwargs: object) -> float:
    """scipy's brentq, imported on first use: scipy.optimize costs 0.7 s of every process that
    imports this module (every `hil` command does, through the scenario's sections) and most
    never solve for a curvature."""
    from scipy.optimize import brentq as solve

    return float(solve(*args, **kwargs))  # type: ignore[arg-type]


@dataclass(frozen=True)
class SegmentModel:
    """Segment and circuit parameters (defaults as the FeaSegment FMU) in SI units."""

    length: float = 0.06
    k_bend: float = 0.025
    d_bend: float = 6e-3
    G_a: float = 7.7e-7
    V_dead: float = 5e-6
    V_ch0: float = 8e-6
    C_a: float = 1e-10
    bore: float = 0.0254
    stroke: float = 0.05
    x_seal: float = 0.025
    p_atm: float = 101325.0
    vacuum_factor: float = 0.5
    p_collapse: float = 1e4
    theta_max: float = 1.6

    @property
    def bore_area(self) -> float:
        return math.pi * self.bore**2 / 4.0

    def bend_sensitivity(self, gauge: float) -> float:
        """dV/dtheta of a channel at gauge pressure `gauge` [Pa]: G_a under pressure, collapsing
        towards vacuum_factor G_a under vacuum [m^3/rad]."""
        if gauge >= 0.0:
            return self.G_a
        beta = self.vacuum_factor
        return self.G_a * (beta + (1.0 - beta) * math.exp(gauge / self.p_collapse))

    def channel_torque(self, gauge: float) -> float:
        """H(g), the integral of the bend sensitivity from 0 to `gauge` [Pa]: a channel's
        torque [N m]."""
        if gauge >= 0.0:
            return self.G_a * gauge
        beta, pc = self.vacuum_factor, self.p_collapse
        return self.G_a * (beta * gauge + (1.0 - beta) * pc * math.expm1(gauge / pc))

    def _rigid_volume(self, swept: float) -> float:
        return self.bore_area * swept + self.V_dead + self.V_ch0

    def side_pressure(self, x_piston: float, theta: float, side: int) -> float:
        """Isothermal gauge pressure [Pa] of side 0 (a: swept stroke - x, bends positive) or 1
        (b: swept x) at piston position `x_piston` [m] and bend angle `theta` [rad].

        The side was sealed at p_atm, unbent, with the piston at x_seal, so
        (p_atm + g) V(g) = p_atm V_seal with V(g) = V_rigid + sign G(g) theta + C_a g, which is
        increasing in g (the FMU checks it at initialisation); solved by bisection."""
        sign = 1.0 if side == 0 else -1.0
        swept = (lambda x: self.stroke - x) if side == 0 else (lambda x: x)
        rigid = self._rigid_volume(swept(x_piston))
        mass_term = self.p_atm * self._rigid_volume(swept(self.x_seal))  # p V at sealing

        def residual(g: float) -> float:
            volume = rigid + sign * self.bend_sensitivity(g) * theta + self.C_a * g
            return (self.p_atm + g) * volume - mass_term

        if residual(0.0) >= 0.0:
            return brentq(residual, -self.p_atm, 0.0, xtol=1e-9, rtol=1e-15)
        # under pressure G = G_a, so the volume is at least V_rigid + sign G_a theta
        upper = mass_term / (rigid + sign * self.G_a * theta) - self.p_atm
        return brentq(residual, 0.0, upper, xtol=1e-9, rtol=1e-15)

    def net_torque(self, x_piston: float, theta: float) -> float:
        """Static torque on the segment at rest at `theta` [rad]: H(g_a) - H(g_b) - k theta
        [N m]; it falls as theta grows (the gas and the spring both resist the bend)."""
        return (
            self.channel_torque(self.side_pressure(x_piston, theta, 0))
            - self.channel_torque(self.side_pressure(x_piston, theta, 1))
            - self.k_bend * theta
        )

    def equilibrium_curvature(self, x_piston: float) -> float:
        """Static equilibrium curvature [1/m] at piston position `x_piston` [m], on the
        mechanical limit theta_max / length if the torque presses the segment against it.

        Raises ValueError naming x_piston outside the stroke."""
        if not 0.0 <= x_piston <= self.stroke:
            raise ValueError(f"x_piston = {x_piston!r} m is outside the stroke [0, {self.stroke}]")
        limit = self.theta_max
        if self.net_torque(x_piston, limit) >= 0.0:
            return limit / self.length
        if self.net_torque(x_piston, -limit) <= 0.0:
            return -limit / self.length
        theta = brentq(
            lambda angle: self.net_torque(x_piston, angle), -limit, limit, xtol=1e-13, rtol=1e-14
        )
        return theta / self.length

    def piston_for_curvature(self, kappa: float) -> float:
        """The piston position [m] whose static equilibrium is curvature `kappa` [1/m] (the
        inverse of equilibrium_curvature, which rises with x); ValueError beyond the reachable
        range."""
        lo, hi = self.reachable_curvature()
        if not lo <= kappa <= hi:
            raise ValueError(
                f"curvature {kappa:g} 1/m is outside the reachable [{lo:.4g}, {hi:.4g}]"
            )
        if self.equilibrium_curvature(0.0) == kappa:
            return 0.0
        return float(
            brentq(
                lambda x: self.equilibrium_curvature(x) - kappa,
                0.0,
                self.stroke,
                xtol=1e-12,
            )
        )

    def reachable_curvature(self) -> tuple[float, float]:
        """(kappa_min, kappa_max) [1/m]: the equilibria with the piston at x = 0 and x = stroke,
        the segment's whole static range."""
        return self.equilibrium_curvature(0.0), self.equilibrium_curvature(self.stroke)

    def pressure_stiffness(self) -> float:
        """Sum over both sides of dp/dV at sealing [Pa/m^3]; side a holds A (stroke - x_seal),
        side b holds A x_seal."""
        total = 0.0
        for swept in (self.stroke - self.x_seal, self.x_seal):
            v_seal = self.bore_area * swept + self.V_dead + self.V_ch0
            total += self.p_atm / (v_seal + self.p_atm * self.C_a)
        return total

    def gas_stiffness(self) -> float:
        """Bending stiffness added by the closed gas circuits [N m/rad]."""
        return self.pressure_stiffness() * self.G_a**2

    def static_gain(self) -> float:
        """d kappa / d x_piston at equilibrium [(1/m)/m]."""
        torque_per_metre = self.pressure_stiffness() * self.G_a * self.bore_area
        return torque_per_metre / (self.length * (self.k_bend + self.gas_stiffness()))

    def time_constant(self) -> float:
        """The lag of the overdamped bend [s]."""
        return self.d_bend / (self.k_bend + self.gas_stiffness())


@dataclass(frozen=True)
class PiGains:
    """Kp [m per 1/m], Ki [m per (1/m) s]."""

    Kp: float
    Ki: float


def design_pi(model: SegmentModel, crossover_hz: float = 2.0) -> PiGains:
    """Pole-zero cancelling PI for the given crossover. 2 Hz keeps the loop well inside what the
    drive can follow (50 mm/s moves the curvature by K * 0.05 ~ 40 1/m/s) and leaves ~75 deg of
    phase margin after the 10 ms control period, one period of computation delay and ~6 ms of
    camera latency (together ~25 ms, 18 deg at 2 Hz)."""
    wc = 2.0 * math.pi * crossover_hz
    tau = model.time_constant()
    Kp = wc * tau / model.static_gain()
    return PiGains(Kp=Kp, Ki=Kp / tau)


@dataclass(frozen=True)
class ArmGains:
    """The curvature loops of a multibody arm as one (`controllers.loop_design.arm_loop_gains`),
    scheduled on the arm's mass matrix M(q) at the estimated configuration: in torque per piston
    travel T_i, for the errors e = theta_ref - theta of the bend angles,
        T x = (3 p^2 M + wc D) e + (wc K + p^3 M) integral(e) - 3 p M theta'
              + (D + 3 p M) theta_ref' + M theta_ref''   (the last two on a planned move),
    D, K the bends' damping and stiffness (with the gas's), wc the crossover and p the
    closed-loop pole of the inertial part. Per-segment values, segment 1 first."""

    crossover: float  # wc [rad/s]
    pole: float  # p [rad/s]
    lengths: tuple[float, ...]  # [m]
    masses: tuple[float, ...]  # [kg]
    torque: tuple[float, ...]  # T: torque per piston travel at the seal [N m/m]
    damping: tuple[float, ...]  # d [N m s/rad]
    stiffness: tuple[float, ...]  # k + k_gas [N m/rad]

    def mass_matrix(self, kappa: Sequence[float]) -> np.ndarray:
        """M at the curvatures `kappa` [kg m^2]."""
        return kinematics.mass_matrix(kappa, self.lengths, self.masses)

    def _per_curvature(self, matrix: np.ndarray) -> np.ndarray:
        """A torque-per-bend-angle matrix as pistons per curvature: T_i^-1 matrix_ij L_j."""
        return matrix * np.outer(1.0 / np.asarray(self.torque), self.lengths)

    def terms(
        self,
        kappa: Sequence[float],
        error: Sequence[float],
        rate: Sequence[float],
        motion: tuple[Sequence[float] | np.ndarray, Sequence[float] | np.ndarray] | None = None,
    ) -> list[tuple[float, float, float]]:
        """Each segment's proportional (with the move's feedforward), integral-rate and damping
        terms [m, m/s, m] from the estimated curvatures, the curvature errors and rates, and
        the references' rate and acceleration on a planned move."""
        M = self.mass_matrix(kappa)
        wc, p = self.crossover, self.pole
        D, K = np.diag(self.damping), np.diag(self.stiffness)
        e, r = np.asarray(error, dtype=float), np.asarray(rate, dtype=float)
        proportional = self._per_curvature(3.0 * p * p * M + wc * D) @ e
        integral = self._per_curvature(wc * K + p**3 * M) @ e
        damping = self._per_curvature(3.0 * p * M) @ r
        if motion is not None:
            ref_rate, ref_acceleration = (np.asarray(v, dtype=float) for v in motion)
            proportional += self._per_curvature(D + 3.0 * p * M) @ ref_rate
            proportional += self._per_curvature(M) @ ref_acceleration
        return [
            (float(a), float(b), float(c))
            for a, b, c in zip(proportional, integral, damping, strict=True)
        ]


@dataclass
class CurvaturePI:
    """Curvature PI for one segment with static feedforward:
        setpoint = x_mid + kappa_ref / K + Kp e + integral,
    clamped to the stroke. Anti-windup by conditional integration: the integral stops while the
    setpoint is clamped in the error's direction, and while the drive is still slewing towards
    the previous setpoint (it is rate-limited at about 50 mm/s, far slower than the loop) by
    more than `lag_tolerance`.

    Parameters
    ----------
    gains
        PI gains.
    period
        Control period T [s].
    x_mid, x_min, x_max
        Piston position at zero curvature and the usable stroke [m].
    feedforward
        1 / K: piston offset per unit curvature reference [m per 1/m] (0 disables it).
    lag_tolerance
        Piston lag behind the previous setpoint that counts as slewing [m].
    """

    gains: PiGains
    period: float
    x_mid: float
    x_min: float
    x_max: float
    feedforward: float = 0.0
    lag_tolerance: float = 1e-3
    integral: float = 0.0
    previous: float | None = None

    def update(self, kappa_ref: float, kappa_est: float, piston: float | None = None) -> float:
        """One control step from the reference, the estimate and the measured piston: the
        piston setpoint [m]."""
        error = kappa_ref - kappa_est
        proposed = self.integral + self.gains.Ki * error * self.period
        base = self.x_mid + self.feedforward * kappa_ref + self.gains.Kp * error
        unclamped = base + proposed
        setpoint = min(max(unclamped, self.x_min), self.x_max)
        clamped_against = setpoint != unclamped and (unclamped > self.x_max) == (error > 0.0)
        slewing = (
            piston is not None
            and self.previous is not None
            and abs(self.previous - piston) > self.lag_tolerance
        )
        if not clamped_against and not slewing:
            self.integral = proposed
        self.previous = setpoint
        return setpoint

    def update_terms(
        self,
        kappa_ref: float,
        proportional: float,
        integral_rate: float,
        damping: float,
        piston: float | None = None,
    ) -> float:
        """`update` with its terms computed outside (`ArmGains.terms`: the segment's share of
        the whole arm's loop): the piston setpoint [m], the same clamp and anti-windup, the
        integral's direction that of `integral_rate`."""
        proposed = self.integral + integral_rate * self.period
        unclamped = self.x_mid + self.feedforward * kappa_ref + proportional - damping + proposed
        setpoint = min(max(unclamped, self.x_min), self.x_max)
        clamped_against = setpoint != unclamped and (unclamped > self.x_max) == (
            integral_rate > 0.0
        )
        slewing = (
            piston is not None
            and self.previous is not None
            and abs(self.previous - piston) > self.lag_tolerance
        )
        if not clamped_against and not slewing:
            self.integral = proposed
        self.previous = setpoint
        return setpoint
