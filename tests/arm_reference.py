"""An independent formulation of the ArmBody FMU's dynamics, the oracle of tests/test_arm_body.py.

What differs from the C model on purpose: the kinematics is the 4 x 4 transform chain written as
the PCC notes state it, `Rz(gamma) Tz(L_p) Ry(theta/2) Tz(chord) Ry(theta/2) Tz(L_p) Rz(-gamma)`
with gamma from (theta_x, theta_y) (the FMU never forms gamma or the chord); Jacobians and
velocities come from complex-step differentiation of that chain (exact to rounding); Lagrange's
equations are taken in the Christoffel form,
    M q'' = Q - M' q' + dT/dq,   M' = d/dt M(q),   T = q'^T M q' / 2,
with M' and dT/dq by fourth-order central differences (the FMU uses the particle form with
analytic second derivatives); scipy's DOP853 integrates at tight tolerance. The gas is the
explicit isothermal law (C_a = 0, vacuum_factor = 1, so that p = m R T / V in closed form).

The chain is singular at theta = 0 (gamma undefined): the runs keep every segment bent.
Shapes: q is (n,) for n = 2 N bending coordinates (theta_x_1, theta_y_1, theta_x_2, ...).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

STEP_COMPLEX = 1e-30  # complex-step size: the derivative is exact to rounding
STEP_DIFF = 1e-3  # central-difference step [rad] (4th order: truncation ~ STEP_DIFF^4)


@dataclass(frozen=True)
class ArmSpec:
    """A spatial arm's parameters in SI units, per segment from the base (FMU names in `fmu`)."""

    L: tuple[float, ...]
    mass: tuple[float, ...]
    m_end: tuple[float, ...]
    L_p: tuple[float, ...]
    k: tuple[float, ...]
    d: tuple[float, ...]
    G_a: tuple[float, ...]
    g: tuple[float, float, float] = (-9.81, 0.0, 0.0)
    n_nodes: int = 5
    gas: bool = True
    bore: float = 0.03175
    stroke: float = 0.1
    V_dead: float = 1e-5
    V_ch0: float = 5e-5
    x_seal: float = 0.05
    p_atm: float = 101325.0
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def n_segments(self) -> int:
        return len(self.L)

    def fmu(self, q0: np.ndarray) -> dict[str, float]:
        """The FMU's parameters for this arm starting at rest at q0."""
        params: dict[str, float] = {
            "n_segments": self.n_segments,
            "planar": 0,
            "gas": int(self.gas),
            "n_nodes": self.n_nodes,
            "g_x": self.g[0],
            "g_y": self.g[1],
            "g_z": self.g[2],
            "bore": self.bore,
            "stroke": self.stroke,
            "V_dead": self.V_dead,
            "V_ch0": self.V_ch0,
            "x_seal": self.x_seal,
            "p_atm": self.p_atm,
            "C_a": 0.0,
            "vacuum_factor": 1.0,
        }
        for i in range(self.n_segments):
            for name in ("L", "mass", "m_end", "L_p", "k", "d", "G_a"):
                params[f"{name}_{i + 1}"] = getattr(self, name)[i]
            params[f"theta_x_start_{i + 1}"] = float(q0[2 * i])
            params[f"theta_y_start_{i + 1}"] = float(q0[2 * i + 1])
            params[f"x_piston_x_{i + 1}"] = self.x_seal
            params[f"x_piston_y_{i + 1}"] = self.x_seal
        return {**params, **self.extra}


def _rz(c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Rotations about z by the angle of cosine c and sine s: shape c.shape + (4, 4)."""
    out = np.zeros((*c.shape, 4, 4), dtype=complex)
    out[..., 0, 0] = c
    out[..., 0, 1] = -s
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    out[..., 2, 2] = 1.0
    out[..., 3, 3] = 1.0
    return out


def _ry(angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros((*np.shape(angle), 4, 4), dtype=complex)
    out[..., 0, 0] = c
    out[..., 0, 2] = s
    out[..., 2, 0] = -s
    out[..., 2, 2] = c
    out[..., 1, 1] = 1.0
    out[..., 3, 3] = 1.0
    return out


def _tz(d: np.ndarray) -> np.ndarray:
    out = np.zeros((*np.shape(d), 4, 4), dtype=complex)
    for j in range(4):
        out[..., j, j] = 1.0
    out[..., 2, 3] = d
    return out


class ArmReference:
    """Mass points, their positions and the equations of motion of an `ArmSpec`."""

    def __init__(self, spec: ArmSpec) -> None:
        self.spec = spec
        self.n = 2 * spec.n_segments
        nodes, weights = np.polynomial.legendre.leggauss(spec.n_nodes)
        self.fractions = 0.5 * (nodes + 1.0)
        # masses: per segment its nodes, then its endplate
        masses = []
        for i in range(spec.n_segments):
            masses += list(0.5 * weights * spec.mass[i]) + [spec.m_end[i]]
        self.masses = np.array(masses)
        area = np.pi * spec.bore**2 / 4
        self.area = area
        self.v_seal = np.array([area * (spec.stroke - spec.x_seal), area * spec.x_seal])
        self.v_seal += spec.V_dead + spec.V_ch0
        self.mRT = spec.p_atm * self.v_seal  # sealed at p_atm (isothermal: m R T = p V)

    def positions(self, q: np.ndarray) -> np.ndarray:
        """Positions of every mass point, shape q.shape[:-1] + (points, 3); q may be complex."""
        q = np.asarray(q, dtype=complex)
        batch = q.shape[:-1]
        frame = np.broadcast_to(np.eye(4, dtype=complex), (*batch, 4, 4))
        out = []
        for i in range(self.spec.n_segments):
            L, Lp = self.spec.L[i], self.spec.L_p[i]
            u, v = q[..., 2 * i], q[..., 2 * i + 1]
            theta = np.sqrt(u * u + v * v)
            cg, sg = u / theta, v / theta
            # a node at the fraction f of the arc is the origin moved by Rz(gamma) Tz(L_p)
            # Ry(th / 2) Tz(chord) for the bend th = f theta of the arc f L long before it
            th = theta[..., None] * self.fractions
            chord = 2.0 * (self.fractions * L / th) * np.sin(th / 2)
            lateral = chord * np.sin(th / 2)
            local = np.stack(
                [cg[..., None] * lateral, sg[..., None] * lateral, Lp + chord * np.cos(th / 2)],
                axis=-1,
            )
            out.append(np.einsum("...ij,...pj->...pi", frame[..., :3, :3], local))
            out[-1] += frame[..., None, :3, 3]
            chord_tip = 2.0 * (L / theta) * np.sin(theta / 2)
            segment = (
                _rz(cg, sg)
                @ _tz(np.full(theta.shape, Lp))
                @ _ry(theta / 2)
                @ _tz(chord_tip)
                @ _ry(theta / 2)
                @ _tz(np.full(theta.shape, Lp))
                @ _rz(cg, -sg)
            )
            frame = frame @ segment
            out.append(frame[..., None, :3, 3])
        return np.concatenate(out, axis=-2)

    def jacobians(self, q: np.ndarray) -> np.ndarray:
        """dp/dq of every point at the configurations q (batch, n): shape (batch, points, 3, n)."""
        q = np.atleast_2d(q)
        probes = q[:, None, :] + 1j * STEP_COMPLEX * np.eye(self.n)[None, :, :]
        p = self.positions(probes)  # (batch, n, points, 3)
        return np.moveaxis(p.imag / STEP_COMPLEX, 1, -1)

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """M(q) = sum m J^T J, shape (batch, n, n) for q of shape (batch, n)."""
        J = self.jacobians(q)
        return np.einsum("p,bpin,bpim->bnm", self.masses, J, J)

    def velocities(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Point velocities J q' at configurations q (batch, n): shape (batch, points, 3)."""
        return self.positions(q + 1j * STEP_COMPLEX * qd).imag / STEP_COMPLEX

    def gas_torque(self, q: np.ndarray) -> np.ndarray:
        """G_a (p_a - p_b) per coordinate, pistons at the sealing position (explicit law)."""
        if not self.spec.gas:
            return np.zeros(self.n)
        G = np.repeat(np.asarray(self.spec.G_a), 2)
        p_a = self.mRT[0] / (self.v_seal[0] + G * q)
        p_b = self.mRT[1] / (self.v_seal[1] - G * q)
        return G * (p_a - p_b)

    def energy(self, q: np.ndarray, qd: np.ndarray) -> float:
        """Kinetic + gravitational + elastic + gas energy [J] (gas relative to the sealed state)."""
        M = self.mass_matrix(q)[0]
        g = np.asarray(self.spec.g)
        p = self.positions(q).real
        k = np.repeat(np.asarray(self.spec.k), 2)
        total = 0.5 * qd @ M @ qd - np.sum(self.masses * (p @ g)) + 0.5 * np.sum(k * q * q)
        if self.spec.gas:
            G = np.repeat(np.asarray(self.spec.G_a), 2)
            for side, sign in ((0, 1.0), (1, -1.0)):
                V = self.v_seal[side] + sign * G * q
                r = V / self.v_seal[side] - 1.0
                total += np.sum(
                    self.spec.p_atm * self.v_seal[side] * r - self.mRT[side] * np.log1p(r)
                )
        return float(total)

    def acceleration(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """q'' from M q'' = Q - M' q' + dT/dq."""
        n, h = self.n, STEP_DIFF
        offsets = np.array([2.0, 1.0, -1.0, -2.0])
        weights = np.array([-1.0, 8.0, -8.0, 1.0]) / (12.0 * h)
        speed = np.linalg.norm(qd)
        direction = qd / speed if speed > 0 else np.zeros(n)
        # one batch of complex probes: each coordinate at q and at the four points along q'
        # (for M and M'), and q' at the four points along each coordinate (for dT/dq)
        along = q + h * offsets[:, None] * direction
        bases = np.vstack([q[None, :], along])  # (5, n)
        probe_J = bases[:, None, :] + 1j * STEP_COMPLEX * np.eye(n)[None, :, :]
        axes = q + h * (offsets[:, None, None] * np.eye(n)[None, :, :]).reshape(-1, n)
        probe_v = axes + 1j * STEP_COMPLEX * qd
        p = self.positions(np.vstack([probe_J.reshape(-1, n), probe_v])).imag / STEP_COMPLEX
        J = np.moveaxis(p[: 5 * n].reshape(5, n, -1, 3), 1, -1)  # (5, points, 3, n)
        Ms = np.einsum("p,bpin,bpim->bnm", self.masses, J, J)
        M, M_dot = Ms[0], np.einsum("o,oij->ij", weights, Ms[1:]) * speed
        v = p[5 * n :]  # (4 n, points, 3)
        T = 0.5 * np.einsum("p,bpi,bpi->b", self.masses, v, v).reshape(4, n)
        dT_dq = weights @ T
        gravity = np.einsum("p,pin,i->n", self.masses, J[0], np.asarray(self.spec.g))
        k = np.repeat(np.asarray(self.spec.k), 2)
        d = np.repeat(np.asarray(self.spec.d), 2)
        Q = gravity - k * q - d * qd + self.gas_torque(q)
        return np.linalg.solve(M, Q - M_dot @ qd + dT_dq)

    def simulate(self, q0: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """q and q' at `times` from rest at q0: shapes (len(times), n)."""
        n = self.n

        def rhs(_t: float, y: np.ndarray) -> np.ndarray:
            return np.concatenate([y[n:], self.acceleration(y[:n], y[n:])])

        y0 = np.concatenate([q0, np.zeros(n)])
        sol = solve_ivp(
            rhs, (times[0], times[-1]), y0, method="DOP853", t_eval=times, rtol=1e-9, atol=1e-10
        )
        assert sol.success, sol.message
        return sol.y[:n].T, sol.y[n:].T
