"""The spatial arm's linearised dynamics about a rest, for the estimator's prediction and the
controller's active damping: the mass matrix M(q) = sum m_k J_k^T J_k over the arm's masses (every
segment's `n_nodes` Gauss-Legendre arc nodes, mass `mass` w_k, and its endplate `m_end`, as
ArmBody lumps them), the static stiffness H (statics.stiffness: bending, gravity, the closed gas
circuits at fixed pistons), the bending damping D = diag(d), and from them the modes of
M e'' + D e' + H e = 0 and a damping matrix that gives the slow modes a chosen damping ratio.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.linalg import eigh, expm

from robots.spatial_arm.controller.kinematics import Stations, points
from robots.spatial_arm.controller.model import ArmModel


@lru_cache(maxsize=8)
def _masses(model: ArmModel) -> tuple[Stations, np.ndarray]:
    xi, w = model.nodes
    seg, frac, mass = [], [], []
    for i in range(model.n_segments):
        for f, wk in zip(xi, w, strict=True):
            seg.append(i)
            frac.append(f)
            mass.append(model.mass[i] * wk)
        seg.append(i)
        frac.append(np.nan)  # the endplate, at the tip frame's origin
        mass.append(model.m_end[i])
    n = len(seg)
    return Stations(np.array(seg), np.array(frac), np.zeros(n)), np.array(mass)


def mass_matrix(model: ArmModel, q: np.ndarray) -> np.ndarray:
    """M(q) (n_q, n_q) [kg m^2]."""
    where, m = _masses(model)
    _, J = points(model, np.asarray(q, dtype=float), where, jacobian=True)
    assert J is not None
    return np.einsum("p,pia,pib->ab", m, J, J)


def damping_matrix(model: ArmModel) -> np.ndarray:
    """D = diag(d) per coordinate [N m s/rad]."""
    return np.diag(np.repeat(np.asarray(model.d), model.n_dof))


def modes(M: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undamped angular frequencies [rad/s] (ascending) and mass-normalised mode shapes."""
    lam, shapes = eigh(H, M)
    return np.sqrt(np.maximum(lam, 0.0)), shapes


def modal_damping(M: np.ndarray, H: np.ndarray, ratio: float, below: float) -> np.ndarray:
    """C such that every mode below `below` [rad/s] gains damping ratio `ratio` (C = M Phi
    diag(2 ratio omega) Phi^T M on those modes, zero on the faster ones, which the loop's delays
    would not damp)."""
    omega, shapes = modes(M, H)
    gain = np.where(omega < below, 2.0 * ratio * omega, 0.0)
    left = M @ shapes
    return np.asarray((left * gain) @ left.T)


def transition(M: np.ndarray, H: np.ndarray, D: np.ndarray, dt: float) -> np.ndarray:
    """exp(A dt) of the state (e, e'), A = [[0, I], [-M^-1 H, -M^-1 D]]."""
    n = len(M)
    A = np.zeros((2 * n, 2 * n))
    A[:n, n:] = np.eye(n)
    A[n:, :n] = -np.linalg.solve(M, H)
    A[n:, n:] = -np.linalg.solve(M, D)
    return np.asarray(expm(A * dt))
