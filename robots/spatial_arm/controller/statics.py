"""The spatial arm at rest: gravity's generalised force, the gas torques, the potential whose
minima are the static equilibria, and the pistons that hold a shape.

At rest ArmBody's equations of motion (fmus/ArmBody/README.md) reduce to

    K q + G(q) = tau_gas(q, x),   G(q) = dE_gravity/dq,   E_gravity = -sum_k m_k g . p_k(q),

the sum over every segment's `n_nodes` Gauss-Legendre arc nodes (mass `mass` w_k each) and its
endplate (`m_end`, at the tip frame's origin), and tau_gas_j = tau(q_j, x_j) the gas torque of
coordinate j's own pair (gas.py). G comes analytically from one walk each way: a segment's
points move with its coordinate a by R_s dr/da, and everything beyond it by R_s (dr_tip/da +
dR_loc/da y), so G_(s,a) = -(R_s^T g) . (dS_s/da + M_s dr_tip/da + dR_loc/da Y_s), with S_s the
first moment of s's own points in its frame, M_s the mass beyond it and Y_s that mass's first
moment about the next segment's base in the next segment's frame (Y_s = S_(s+1) + M_(s+1)
r_tip_(s+1) + R_loc_(s+1) Y_(s+1)). Its Jacobian (the gravity stiffness, the Hessian of
E_gravity) is G's complex-step derivative, exact to rounding (kinematics.py's functions are
complex-analytic).

The total potential at fixed pistons, U = E_gravity + sum k theta^2 / 2 + E_gas (ArmBody's E_gas,
whose slope in theta is -tau_gas), has the residual as its gradient and `stiffness` as its
Hessian: equilibrium.py finds its minima.

`pistons_for` inverts the actuation: the pair's torque rises monotonically with its piston, so
each coordinate's piston is a 1-D root in [0, stroke] (safeguarded Newton), NaN where the torque
needed lies outside what the stroke can give.

Shapes: q and pistons (..., n_q), vectorised over any batch shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robots.spatial_arm.controller import gas
from robots.spatial_arm.controller.kinematics import arc_point, chain, tip_point
from robots.spatial_arm.controller.model import ArmModel

STEP_COMPLEX = 1e-30
PISTON_TOLERANCE = 1e-14  # [m]
PISTON_ITERATIONS = 60


# ------------------------------------------------------------------ gravity


def _own_points(model: ArmModel, u: np.ndarray, v: np.ndarray):
    """Per segment: its own points' mass-weighted sums in its frame, S (..., N, 3) and dS/du,
    dS/dv, its tip point r_tip and derivatives."""
    xi, w = model.nodes
    L = np.asarray(model.L)[:, None]
    L_p = np.asarray(model.L_p)[:, None]
    m_node = np.asarray(model.mass)[:, None] * w  # (N, K)
    r, du, dv = arc_point(L, L_p, xi, u[..., None], v[..., None])  # (..., N, K, 3)
    rt, dut, dvt, _ = tip_point(np.asarray(model.L), np.asarray(model.L_p), u, v)
    m_end = np.asarray(model.m_end)[:, None]
    weigh = m_node[..., None]

    def moment(nodes: np.ndarray, tip_value: np.ndarray) -> np.ndarray:
        return np.sum(weigh * nodes, axis=-2) + m_end * tip_value

    return moment(r, rt), moment(du, dut), moment(dv, dvt), rt, (dut, dvt)


def gravity(model: ArmModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """E_gravity (...,) [J] and G(q) = dE_gravity/dq (..., n_q) [N m]."""
    c = chain(model, q)
    S, dSu, dSv, rt, (dut, dvt) = _own_points(model, c.u, c.v)
    n = model.n_segments
    own_mass = np.asarray(model.mass) + np.asarray(model.m_end)
    beyond = np.concatenate([np.cumsum(own_mass[::-1])[::-1][1:], [0.0]])  # M_s
    g = model.g
    g_local = np.einsum("...sji,j->...si", c.R[..., :n, :, :], g)  # R_s^T g
    energy = -(np.einsum("s,...sj,j->...", own_mass, c.P[..., :n, :], g))
    energy = energy - np.einsum("...si,...si->...", g_local, S)
    rot = np.swapaxes(c.R[..., :n, :, :], -1, -2) @ c.R[..., 1:, :, :]  # R_loc
    Y = np.zeros_like(S)
    for s in range(n - 2, -1, -1):
        nxt = s + 1
        Y[..., s, :] = (
            S[..., nxt, :]
            + beyond[nxt] * rt[..., nxt, :]
            + np.einsum("...ij,...j->...i", rot[..., nxt, :, :], Y[..., nxt, :])
        )
    force = np.empty((*S.shape[:-1], 2), dtype=S.dtype)
    for a, (dS, dr) in enumerate(((dSu, dut), (dSv, dvt))):
        turned = np.einsum("...sij,...sj->...si", c.rot_d[..., a, :, :], Y)
        total = dS + beyond[:, None] * dr + turned
        force[..., a] = -np.einsum("...si,...si->...s", g_local, total)
    return energy, model.reduce(force)


def gravity_stiffness(model: ArmModel, q: np.ndarray) -> np.ndarray:
    """dG/dq (..., n_q, n_q), the Hessian of E_gravity, by complex-step differentiation of G."""
    q = np.asarray(q, dtype=float)
    n = model.n_q
    probes = q[..., None, :] + 1j * STEP_COMPLEX * np.eye(n)
    _, G = gravity(model, probes)
    return G.imag / STEP_COMPLEX


# ------------------------------------------------------------------ gas and potential


def _G_a(model: ArmModel) -> np.ndarray:
    return np.repeat(np.asarray(model.G_a), model.n_dof)


def gas_torque(model: ArmModel, q: np.ndarray, pistons: np.ndarray) -> gas.PairTorque:
    """Every pair's torque on its own coordinate at q and the pistons, with its slopes."""
    return gas.torque(model, _G_a(model), q, pistons)


def potential(model: ArmModel, q: np.ndarray, pistons: np.ndarray) -> np.ndarray:
    """U = E_gravity + E_elastic + E_gas (...,) [J] at fixed pistons."""
    E_g, _ = gravity(model, q)
    elastic = 0.5 * np.sum(model.stiffness * np.asarray(q) ** 2, axis=-1)
    return E_g + elastic + np.sum(gas.energy(model, _G_a(model), q, pistons), axis=-1)


def residual(model: ArmModel, q: np.ndarray, pistons: np.ndarray) -> np.ndarray:
    """K q + G(q) - tau_gas(q, x) (..., n_q) [N m]: zero at a static equilibrium (= dU/dq)."""
    _, G = gravity(model, q)
    return model.stiffness * q + G - gas_torque(model, q, pistons).tau


def stiffness(model: ArmModel, q: np.ndarray, pistons: np.ndarray) -> np.ndarray:
    """The Hessian of U: K + dG/dq - diag(dtau/dtheta) (..., n_q, n_q) [N m/rad]."""
    H = gravity_stiffness(model, q)
    diag = model.stiffness - gas_torque(model, q, pistons).d_theta
    return H + diag[..., None] * np.eye(model.n_q)


# ------------------------------------------------------------------ the pistons for a shape


@dataclass(frozen=True)
class Pistons:
    """The piston positions holding q at rest (..., n_q) [m], NaN where the stroke cannot;
    `inside` where it can; the torque each pair must give [N m] and the range the stroke spans
    at that bend, tau(theta, 0) and tau(theta, stroke)."""

    x: np.ndarray
    inside: np.ndarray
    tau: np.ndarray
    tau_min: np.ndarray
    tau_max: np.ndarray

    @property
    def all_inside(self) -> np.ndarray:
        return np.all(self.inside, axis=-1)


def required_torque(model: ArmModel, q: np.ndarray) -> np.ndarray:
    """K q + G(q): the torque each pair must give to hold q at rest (..., n_q) [N m]."""
    _, G = gravity(model, q)
    return model.stiffness * np.asarray(q) + G


def pistons_for(model: ArmModel, q: np.ndarray) -> Pistons:
    """The pistons whose gas torques hold q at rest: per coordinate the root in [0, stroke] of
    tau(theta_j, x) = (K q + G(q))_j, increasing in x (safeguarded Newton)."""
    q = np.asarray(q, dtype=float)
    need = required_torque(model, q)
    G_a = _G_a(model)
    lo = np.zeros_like(q)
    hi = np.full_like(q, model.stroke)
    t_lo = gas.torque(model, G_a, q, lo).tau
    t_hi = gas.torque(model, G_a, q, hi).tau
    inside = (t_lo <= need) & (need <= t_hi)
    span = np.where(t_hi > t_lo, t_hi - t_lo, 1.0)
    x = np.clip((need - t_lo) / span, 0.0, 1.0) * model.stroke
    for _ in range(PISTON_ITERATIONS):
        t = gas.torque(model, G_a, q, x)
        f = t.tau - need
        lo = np.where(f < 0.0, x, lo)
        hi = np.where(f > 0.0, x, hi)
        nxt = x - f / t.d_x
        nxt = np.where((nxt > lo) & (nxt < hi), nxt, 0.5 * (lo + hi))
        change = np.abs(nxt - x)
        x = nxt
        if np.all(~inside | (change <= PISTON_TOLERANCE)):
            break
    return Pistons(
        x=np.where(inside, x, np.nan), inside=inside, tau=need, tau_min=t_lo, tau_max=t_hi
    )
