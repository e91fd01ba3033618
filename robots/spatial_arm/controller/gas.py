"""A channel pair's closed gas circuit, ArmBody's law (fmus/common/gas_circuit.c, isothermal).

Side a and b of the pair on coordinate theta (its segment's G_a) at piston position x: cylinder
chamber + tubing + channel of volume

    V = A s(x) + V_dead + V_ch0 + sign G(g) theta + C_a g,   s_a = stroke - x, s_b = x,

sign +1 (a) / -1 (b), at gauge pressure g, sealed at p_atm with the piston at x_seal and the arm
straight: (p_atm + g) V = p_atm V_seal. G(g) = G_a under pressure and G_a (f + (1 - f)
exp(g / p_collapse)) under vacuum (f = vacuum_factor: the channel partly collapses), and the
pair's torque on theta is H(g_a) - H(g_b), H(g) = int_0^g G. Under pressure the volume law is a
quadratic in g (its stable root, as gas_circuit.c); under vacuum Newton from that root, here run
to convergence (gas_circuit.c stops once a step is below 1e-3 Pa, 1e-10 Pa from the root).

The torque rises with x at a fixed bend (side a compressed, b expanded) and falls with theta
(the gas's stiffness): `torque` returns both slopes by implicit differentiation of the volume law.
Everything is vectorised over broadcasting arrays of G_a, theta and x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from robots.spatial_arm.controller.model import ArmModel

SIGNS = (1.0, -1.0)
VACUUM_ITERATIONS = 60
VACUUM_STEP = 1e-9  # [Pa] a Newton step below this ends the vacuum solve


@dataclass(frozen=True)
class Side:
    """One side's state: gauge pressure [Pa], G(g) [m^3/rad], H(g) [N m], volume [m^3] and the
    derivative of the volume law F = (p_atm + g) V - m R T in g."""

    g: np.ndarray
    G: np.ndarray
    H: np.ndarray
    V: np.ndarray
    dF_dg: np.ndarray


def channel(model: ArmModel, G_a: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, ...]:
    """G(g), H(g) and dG/dg of a channel at gauge pressure g."""
    f, pc = model.vacuum_factor, model.p_collapse
    gv = np.minimum(g, 0.0)
    em1 = np.expm1(gv / pc)
    vacuum = g < 0.0
    G = np.where(vacuum, G_a * (f + (1.0 - f) * (1.0 + em1)), G_a)
    H = np.where(vacuum, G_a * (f * gv + (1.0 - f) * pc * em1), G_a * g)
    dG = np.where(vacuum, G_a * (1.0 - f) / pc * (1.0 + em1), 0.0)
    return G, H, dG


def side_state(
    model: ArmModel, G_a: np.ndarray, theta: np.ndarray, x: np.ndarray, side: int
) -> Side:
    """Side `side` (0: a, 1: b) of the pair at bend theta and piston x."""
    sign = SIGNS[side]
    swept = model.stroke - x if side == 0 else x
    V0 = model.area * swept + model.V_dead + model.V_ch0
    mRT = model.p_atm * model.sealed_volume[side]
    p_atm, C = model.p_atm, model.C_a
    V1 = V0 + sign * G_a * theta
    B = C * p_atm + V1
    c0 = p_atm * V1 - mRT
    g = -2.0 * c0 / (B + np.sqrt(B * B - 4.0 * C * c0))
    active = g < 0.0
    for _ in range(VACUUM_ITERATIONS):
        if not np.any(active):
            break
        G, _, dG = channel(model, G_a, g)
        p = p_atm + g
        vol = V0 + sign * G * theta + C * g
        step = (p * vol - mRT) / (vol + p * (C + sign * dG * theta))
        g = np.where(active, g - step, g)
        active = active & (np.abs(step) > VACUUM_STEP)
    if np.any(active):
        raise ArithmeticError("gas: a vacuum side's pressure did not converge")
    G, H, dG = channel(model, G_a, g)
    p = p_atm + g
    V = V0 + sign * G * theta + C * g
    return Side(g=g, G=G, H=H, V=V, dF_dg=V + p * (C + sign * dG * theta))


@dataclass(frozen=True)
class PairTorque:
    """The pair's torque on its coordinate [N m] and its slopes in the bend [N m/rad] and the
    piston [N m/m]; the two sides' gauge pressures [Pa]."""

    tau: np.ndarray
    d_theta: np.ndarray
    d_x: np.ndarray
    p_a: np.ndarray
    p_b: np.ndarray


def torque(
    model: ArmModel, G_a: npt.ArrayLike, theta: npt.ArrayLike, x: npt.ArrayLike
) -> PairTorque:
    """Torque H(g_a) - H(g_b) of the pair at bend theta and piston x, with its slopes: g moves
    with theta and x along F = 0, dg = -(dF/dtheta dtheta + dF/dx dx) / dF/dg, dF/dtheta = p sign
    G(g), dF/dx = p dV0/dx (-A for a, +A for b), and dH/dg = G."""
    G_a, theta, x = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (G_a, theta, x)))
    a = side_state(model, G_a, theta, x, 0)
    b = side_state(model, G_a, theta, x, 1)
    p_a, p_b = model.p_atm + a.g, model.p_atm + b.g
    ga_theta = -p_a * a.G / a.dF_dg
    gb_theta = p_b * b.G / b.dF_dg
    ga_x = p_a * model.area / a.dF_dg
    gb_x = -p_b * model.area / b.dF_dg
    return PairTorque(
        tau=a.H - b.H,
        d_theta=a.G * ga_theta - b.G * gb_theta,
        d_x=a.G * ga_x - b.G * gb_x,
        p_a=a.g,
        p_b=b.g,
    )


def energy(
    model: ArmModel, G_a: npt.ArrayLike, theta: npt.ArrayLike, x: npt.ArrayLike
) -> np.ndarray:
    """The pair's stored energy [J]: the gas's isothermal free energy relative to its sealed
    state, p_atm V_s r - m R T ln(1 + r) with r = V / V_s - 1, plus the channel walls' C_a g^2 /
    2 + sign theta (g G - H), ArmBody's E_gas. At a fixed x its slope in theta is -tau."""
    G_a, theta, x = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (G_a, theta, x)))
    total = np.zeros(theta.shape)
    for side in (0, 1):
        s = side_state(model, G_a, theta, x, side)
        V_s = model.sealed_volume[side]
        r = s.V / V_s - 1.0
        total += model.p_atm * V_s * r - model.p_atm * V_s * np.log1p(r)
        total += 0.5 * model.C_a * s.g**2 + SIGNS[side] * theta * (s.g * s.G - s.H)
    return total
