"""Static equilibria of the spatial arm at given pistons, the bend limit included.

At fixed pistons x the equilibria are the stationary points of the total potential U(q) =
E_gravity + sum k theta^2 / 2 + E_gas (statics.py); the damped arm settles into a minimum. With
the bend limit |theta_s| <= theta_max (ArmBody's: a segment reaching it rests there, held by a
reaction along its normal), the arm's rest is a minimum of U on that set.

Method: Newton's method on U, globalised: the Newton matrix is U's Hessian (statics.stiffness),
its eigenvalues taken in magnitude and floored so that every step descends; each step is capped
at MAX_STEP per coordinate and halved until U falls (Armijo, within rounding). From a nearby
start it therefore converges to the minimum the damped dynamics would reach. The limit is an
active set: a segment found beyond theta_max is put on it, parametrised by its bending direction
gamma alone ((theta_x, theta_y) = theta_max (cos gamma, sin gamma); planar: held at +-theta_max),
and Newton runs again in those reduced coordinates (gradient D^T r, Hessian D^T H D plus the
curvature of the circle, -r_s . q_s); a segment whose reaction -n . r_s turns negative (U falls
inwards) is released; until no segment changes.

The Hessian of the gravity term is a complex-step derivative (statics.gravity_stiffness), most of an
iteration's cost; a row whose last step was full and below REUSE_BELOW keeps its Hessian
(Shamanskii's variant of Newton: the stale Hessian still contracts the error by O(step) per step).
Measured on the default arm, 3000 uniform piston settings from straight: 3.8 s (5 s with the 2-core
host loaded), residuals below 1e-15 N m, 136 of them resting on a limit. Warm starts from the
nearest solved setting did not pay: in the 8-D piston cube a few thousand samples lie a third of the
stroke apart, and the batch took 7 Newton iterations instead of 8.

Shapes: pistons (..., n_q); the batch is solved together (vectorised), each configuration with
its own step lengths and active set.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from robots.spatial_arm.controller import statics
from robots.spatial_arm.controller.model import ArmModel

NEWTON_ITERATIONS = 60
LINE_SEARCH_HALVINGS = 40
STEP_TOLERANCE = 1e-13  # [rad] a full Newton step below this ends the solve
MAX_STEP = 0.5  # [rad] per coordinate and Newton step
REUSE_BELOW = 1e-2  # [rad] a full step below this keeps the row's Hessian for the next one
EIGEN_FLOOR = 1e-9  # [N m/rad] smallest curvature a Newton step may assume
DUMMY_CURVATURE = 1e6  # [N m/rad] the unused coordinate of a segment on its limit
ARMIJO = 1e-4
LIMIT_ROUNDS = 8
LIMIT_SLACK = 1e-12  # [rad] a bend beyond theta_max by more puts the segment on its limit
REACTION_SLACK = 1e-12  # [N m] a reaction below minus this releases it


@dataclass(frozen=True)
class Equilibrium:
    """Static equilibria (..., n_q) at a batch of pistons: the largest residual left once the
    limits' reactions are counted [N m], converged, the smallest eigenvalue of the (reduced)
    Hessian of U [N m/rad] (> 0: a stable rest), which segments rest on their limit and the
    limits' reactions there (..., N) [N m], and the Newton iterations of the longest solve."""

    q: np.ndarray
    residual: np.ndarray
    converged: np.ndarray
    min_eigenvalue: np.ndarray
    on_limit: np.ndarray
    reaction: np.ndarray
    iterations: int

    @property
    def stable(self) -> np.ndarray:
        return self.min_eigenvalue > 0.0

    @property
    def ok(self) -> np.ndarray:
        """Converged to a stable rest."""
        return self.converged & self.stable


# ------------------------------------------------------------------ reduced coordinates


def _to_q(model: ArmModel, z: np.ndarray, on: np.ndarray) -> np.ndarray:
    """q of the reduced coordinates z (B, n_q): a spatial segment on its limit keeps its
    direction gamma in its first slot; a planar one its fixed bend."""
    if model.planar:
        return z
    full = model.full(z).copy()
    gamma = full[..., 0].copy()
    full[..., 0] = np.where(on, model.theta_max * np.cos(gamma), full[..., 0])
    full[..., 1] = np.where(on, model.theta_max * np.sin(gamma), full[..., 1])
    return model.reduce(full)


def _to_z(model: ArmModel, q: np.ndarray, on: np.ndarray) -> np.ndarray:
    """The reduced coordinates of q (B, n_q) with the segments `on` put on their limit."""
    full = model.full(q).copy()
    if model.planar:
        full[..., 0] = np.where(on, np.sign(full[..., 0]) * model.theta_max, full[..., 0])
        return model.reduce(full)
    gamma = np.arctan2(full[..., 1], full[..., 0])
    full[..., 0] = np.where(on, gamma, full[..., 0])
    full[..., 1] = np.where(on, 0.0, full[..., 1])
    return model.reduce(full)


def _tangent(model: ArmModel, z: np.ndarray, on: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dq/dz (B, n_q, n_q) and the mask of unused reduced coordinates (B, n_q)."""
    n, nd = model.n_q, model.n_dof
    D = np.broadcast_to(np.eye(n), (len(z), n, n)).copy()
    dummy = np.zeros(z.shape, dtype=bool)
    for s in range(model.n_segments):
        i, rows = s * nd, on[:, s]
        if not np.any(rows):
            continue
        dummy[rows, i + nd - 1] = True
        if model.planar:
            D[rows, i, i] = 0.0
            continue
        gamma = z[rows, i]
        D[rows, i, i] = -model.theta_max * np.sin(gamma)
        D[rows, i + 1, i] = model.theta_max * np.cos(gamma)
        D[rows, i + 1, i + 1] = 0.0
    return D, dummy


def reactions(model: ArmModel, q: np.ndarray, r: np.ndarray, on: np.ndarray) -> np.ndarray:
    """The limits' reactions lambda_s = -n_s . r_s (B, N) of the segments `on` (0 elsewhere),
    n_s the outward normal q_s / |q_s|, r the residual dU/dq."""
    qf, rf = model.full(q), model.full(r)
    theta = np.maximum(np.linalg.norm(qf, axis=-1), 1e-300)
    lam = -np.sum(qf * rf, axis=-1) / theta
    return np.where(on, lam, 0.0)


# ------------------------------------------------------------------ Newton


def _gradient(model: ArmModel, z: np.ndarray, x: np.ndarray, on: np.ndarray):
    """q, the residual r = dU/dq, dq/dz, the unused slots, and the gradient D^T r in z."""
    q = _to_q(model, z, on)
    r = statics.residual(model, q, x)
    D, dummy = _tangent(model, z, on)
    return q, r, D, dummy, np.einsum("bji,bj->bi", D, r)


def _hessian(model: ArmModel, x: np.ndarray, on: np.ndarray, q, r, D, dummy):
    """The eigenvalues and eigenvectors of the reduced Hessian D^T H D + the circle's curvature
    (-r_s . q_s along gamma) + DUMMY_CURVATURE on the unused slots."""
    H = statics.stiffness(model, q, x)
    Hz = np.einsum("bji,bjk,bkl->bil", D, H, D)
    curvature = np.zeros(q.shape)
    if not model.planar:
        circle = -np.sum(model.full(r) * model.full(q), axis=-1)
        curvature[:, 0 :: model.n_dof] = np.where(on, circle, 0.0)
    curvature = np.where(dummy, DUMMY_CURVATURE, curvature)
    return np.linalg.eigh(Hz + curvature[..., None] * np.eye(model.n_q))


def _step(lam: np.ndarray, vec: np.ndarray, grad: np.ndarray, dummy: np.ndarray) -> np.ndarray:
    """The modified Newton step: |eigenvalues| floored, capped at MAX_STEP per coordinate."""
    coeff = np.einsum("bji,bj->bi", vec, grad) / np.maximum(np.abs(lam), EIGEN_FLOOR)
    step = np.where(dummy, 0.0, -np.einsum("bij,bj->bi", vec, coeff))
    biggest = np.max(np.abs(step), axis=-1, keepdims=True)
    return step * np.minimum(1.0, MAX_STEP / np.maximum(biggest, 1e-300))


def _line_search(
    U_of: Callable[[np.ndarray, np.ndarray], np.ndarray],
    z: np.ndarray,
    step: np.ndarray,
    slope: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Each row's step halved until U falls by Armijo's rule (within rounding); U_of(z, rows)."""
    rows = np.arange(len(z))
    U = U_of(z, rows)
    alpha = np.ones(len(z))
    pending = np.ones(len(z), dtype=bool)
    out = z.copy()
    slack = 1e-13 * (1.0 + np.abs(U))
    for _ in range(LINE_SEARCH_HALVINGS):
        idx = rows[pending]
        trial = z[idx] + alpha[idx, None] * step[idx]
        good = U_of(trial, idx) <= U[idx] + ARMIJO * alpha[idx] * slope[idx] + slack[idx]
        out[idx[good]] = trial[good]
        pending[idx[good]] = False
        alpha[pending] *= 0.5
        if not np.any(pending):
            break
    alpha[pending] = 0.0
    return out, alpha


def _newton(
    model: ArmModel, x: np.ndarray, z: np.ndarray, on: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """Minimise U in the reduced coordinates with `on` fixed: z, converged, iterations. A row
    whose last step was full and below REUSE_BELOW keeps its Hessian (Shamanskii's variant:
    there the Hessian moves by O(step), so a stale one still contracts the error by that factor
    per step, and the complex-step Hessian is most of an iteration's cost)."""
    z = z.copy()
    n = model.n_q
    active = np.ones(len(z), dtype=bool)
    fresh = np.ones(len(z), dtype=bool)
    lam, vec = np.ones((len(z), n)), np.broadcast_to(np.eye(n), (len(z), n, n)).copy()
    iterations = 0
    while iterations < NEWTON_ITERATIONS and np.any(active):
        iterations += 1
        idx = np.flatnonzero(active)
        za, xa, ona = z[idx], x[idx], on[idx]
        q, r, D, dummy, grad = _gradient(model, za, xa, ona)
        new = fresh[idx]
        if np.any(new):
            rows = idx[new]
            lam[rows], vec[rows] = _hessian(
                model, xa[new], ona[new], q[new], r[new], D[new], dummy[new]
            )
        step = _step(lam[idx], vec[idx], grad, dummy)

        def U_of(
            trial: np.ndarray, rows: np.ndarray, on: np.ndarray = ona, x: np.ndarray = xa
        ) -> np.ndarray:
            return statics.potential(model, _to_q(model, trial, on[rows]), x[rows])

        slope = np.einsum("bi,bi->b", grad, step)
        z[idx], alpha = _line_search(U_of, za, step, slope)
        size = np.max(np.abs(step), axis=-1)
        done = (alpha == 1.0) & (size <= STEP_TOLERANCE)
        fresh[idx] = (alpha < 1.0) | (size > REUSE_BELOW)
        active[idx[done]] = False
    return z, ~active, iterations


def static_equilibrium(
    model: ArmModel, pistons: np.ndarray, q0: np.ndarray | None = None
) -> Equilibrium:
    """The arm's rests at the pistons (..., n_q) [m], each from q0 (default straight; broadcast
    to the pistons' batch): module docstring."""
    pistons = np.asarray(pistons, dtype=float)
    if pistons.shape[-1] != model.n_q:
        raise ValueError(f"pistons: {pistons.shape[-1]} values for the arm's {model.n_q} pairs")
    batch = pistons.shape[:-1]
    x = pistons.reshape(-1, model.n_q)
    start = np.zeros(model.n_q) if q0 is None else np.asarray(q0, dtype=float)
    z = np.array(np.broadcast_to(start, pistons.shape).reshape(x.shape))
    on = np.zeros((len(x), model.n_segments), dtype=bool)
    converged = np.zeros(len(x), dtype=bool)
    todo = np.arange(len(x))
    iterations = 0
    for _ in range(LIMIT_ROUNDS):
        z[todo], converged[todo], used = _newton(model, x[todo], z[todo], on[todo])
        iterations = max(iterations, used)
        q = _to_q(model, z[todo], on[todo])
        lam = reactions(model, q, statics.residual(model, q, x[todo]), on[todo])
        engage = ~on[todo] & (model.bend_angles(q) > model.theta_max + LIMIT_SLACK)
        release = on[todo] & (lam < -REACTION_SLACK)
        changed = np.any(engage | release, axis=-1)
        if not np.any(changed):
            break
        rows = todo[changed]
        on[rows] = (on[rows] | engage[changed]) & ~release[changed]
        z[rows] = _to_z(model, q[changed], on[rows])
        converged[rows] = False
        todo = rows
    return _result(model, x, z, on, converged, iterations, batch)


def _result(model, x, z, on, converged, iterations, batch) -> Equilibrium:
    q = _to_q(model, z, on)
    r = statics.residual(model, q, x)
    lam = reactions(model, q, r, on)
    normal = model.full(q) / np.maximum(model.bend_angles(q), 1e-300)[..., None]
    free = r + model.reduce(lam[..., None] * normal)
    lam_min = _hessian(model, x, on, q, r, *_tangent(model, z, on))[0][:, 0]
    shaped = {"converged": converged, "min_eigenvalue": lam_min}
    return Equilibrium(
        q=q.reshape(*batch, model.n_q),
        residual=np.max(np.abs(free), axis=-1).reshape(batch),
        on_limit=on.reshape(*batch, model.n_segments),
        reaction=lam.reshape(*batch, model.n_segments),
        iterations=iterations,
        **{name: value.reshape(batch) for name, value in shaped.items()},
    )
