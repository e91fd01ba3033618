"""Bending coordinates from 3-D markers: each segment's (theta_x, theta_y) from its tip marker
seen in its base frame, walking from the base (the published Algorithm 2, Marchese et al.,
"Design, kinematics, and control of a soft spatial fluidic elastomer manipulator", IJRR 2016).

One segment. Its tip marker at m = (x, y, z) in the segment's base frame lies, for the bend (u,
v) = theta (cos gamma, sin gamma), at r = (F theta cos gamma, F theta sin gamma, G) with F, G
even functions of theta (kinematics.py; ArmBody's transform with its end pieces). Rotating into
the bending plane, gamma = atan2(y, x) and the in-plane point (d, z), d = hypot(x, y), must lie
on the curve c(theta) = (F theta, G): invert it for theta. With the end pieces that inversion
has no closed form, so theta is the least-squares root

    theta = argmin over [0, theta_max] of (F theta - d)^2 + (G - z)^2,

the best theta on a grid of GRID points, then Gauss-Newton (exact to rounding on noiseless
markers, where the residual vanishes). This is the least-squares fit of all three coordinates:
for any theta > 0, gamma = atan2(y, x) is the closest bending direction (F theta >= 0), so only
the in-plane distance is left. Near zero bend nothing divides: theta -> 0 gives (u, v) -> 0
whatever gamma (atan2(0, 0) = 0), and the lateral term (slope F(0) = L / 2 + L_p) dominates the
axial one (slope 0 at theta = 0) so noise along the axis does not invent a bend. A marker beyond
the reachable curve gives the nearest bend within the limit (clipped to theta_max).
A planar arm bends in its base's x-z plane only: d = x signed, theta over [-theta_max, theta_max]
and y ignored (the least squares of a bend confined to the plane).

The arm (`bends_from_markers`). Segment s's base frame is the previous segment's estimated tip frame
(its fitted bend through the model's kinematics, not the raw marker), from the base frame at the
origin (the base marker, row 0, carries no information: the base is fixed). A NaN marker leaves its
segment and every one after it NaN. The walk carries each segment's error into the next one's frame:
with 1 mm marker noise on the default arm (bends up to 0.8 rad per coordinate) the bends' errors
grow from 0.015 rad (base) to 0.11 rad (tip) rms, the endplates fitted within 1.4-1.9 mm rms.
`fit_markers` fits all bends to all markers at once (Gauss-Newton from the walk with the analytic
marker Jacobian, bends clipped to the limit: the maximum-likelihood estimate under Gaussian noise):
0.014 to 0.093 rad. Positions alone pin a segment's bend only as well as they pin its base frame's
orientation, which the markers before it set: the growth is the geometry's.

Shapes: a batch of marker sets (..., N + 1, 3) gives (..., n_q).
"""

from __future__ import annotations

import numpy as np

from robots.spatial_arm.controller.kinematics import marker_jacobian, tip_point, tip_rotation
from robots.spatial_arm.controller.model import ArmModel

GRID = 33  # starting grid over the bend range
ITERATIONS = 40
STEP_TOLERANCE = 1e-15  # [rad]
FIT_ITERATIONS = 30
FIT_TOLERANCE = 1e-12  # [rad] a fit's step below this ends it
FIT_DAMPING = 1e-9  # [m^2/rad^2] Levenberg-Marquardt floor on J^T J's diagonal, relative


def _curve(L: np.ndarray, L_p: np.ndarray, theta: np.ndarray):
    """The in-plane tip (F theta, G) at bend theta and its derivative in theta."""
    r, du, _, _ = tip_point(L, L_p, theta, np.zeros_like(theta))
    return r[..., 0], r[..., 2], du[..., 0], du[..., 2]


def plane_bend(
    L: np.ndarray, L_p: np.ndarray, d: np.ndarray, z: np.ndarray, lo: float, hi: float
) -> np.ndarray:
    """theta in [lo, hi] minimising (F theta - d)^2 + (G - z)^2 (arrays broadcasting)."""
    L, L_p, d, z = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (L, L_p, d, z)))
    grid = np.linspace(lo, hi, GRID)
    lateral, axial, _, _ = _curve(
        L[..., None], L_p[..., None], np.broadcast_to(grid, (*L.shape, GRID))
    )
    cost = (lateral - d[..., None]) ** 2 + (axial - z[..., None]) ** 2
    theta = grid[np.argmin(cost, axis=-1)]
    for _ in range(ITERATIONS):
        lateral, axial, d_lat, d_ax = _curve(L, L_p, theta)
        e_lat, e_ax = lateral - d, axial - z
        norm = d_lat * d_lat + d_ax * d_ax
        step = (d_lat * e_lat + d_ax * e_ax) / np.where(norm > 0.0, norm, 1.0)
        new = np.clip(theta - step, lo, hi)
        change = np.abs(new - theta)
        theta = new
        if not np.any(change > STEP_TOLERANCE):
            break
    return theta


def segment_bend(model: ArmModel, segment: int, tip_local: np.ndarray) -> np.ndarray:
    """(theta_x, theta_y) of segment `segment` (from 0) from its tip marker in its own base
    frame (..., 3) -> (..., 2) (planar: theta_y 0)."""
    tip_local = np.asarray(tip_local, dtype=float)
    x, y, z = tip_local[..., 0], tip_local[..., 1], tip_local[..., 2]
    L, L_p = np.asarray(model.L[segment]), np.asarray(model.L_p[segment])
    if model.planar:
        theta = plane_bend(L, L_p, x, z, -model.theta_max, model.theta_max)
        return np.stack([theta, np.zeros_like(theta)], axis=-1)
    gamma = np.arctan2(y, x)
    theta = plane_bend(L, L_p, np.hypot(x, y), z, 0.0, model.theta_max)
    return np.stack([theta * np.cos(gamma), theta * np.sin(gamma)], axis=-1)


def bends_from_markers(model: ArmModel, markers: np.ndarray) -> np.ndarray:
    """q (..., n_q) from the base and endplate markers (..., N + 1, 3), walking from the base."""
    markers = np.asarray(markers, dtype=float)
    n = model.n_segments
    if markers.shape[-2:] != (n + 1, 3):
        raise ValueError(f"markers: shape {markers.shape[-2:]}, ({n + 1}, 3) expected")
    batch = markers.shape[:-2]
    R = np.broadcast_to(np.eye(3), (*batch, 3, 3))
    P = np.zeros((*batch, 3))
    out = np.empty((*batch, n, 2))
    for s in range(n):
        local = np.einsum("...ji,...j->...i", R, markers[..., s + 1, :] - P)
        uv = segment_bend(model, s, np.nan_to_num(local))
        uv = np.where(np.isnan(local).any(axis=-1, keepdims=True), np.nan, uv)
        out[..., s, :] = uv
        u, v = uv[..., 0], uv[..., 1]
        r, _, _, fs = tip_point(np.asarray(model.L[s]), np.asarray(model.L_p[s]), u, v)
        rot, _, _ = tip_rotation(u, v, fs)
        P = P + np.einsum("...ij,...j->...i", R, r)
        R = R @ rot
    return model.reduce(out)


def fit_markers(model: ArmModel, markers: np.ndarray, q0: np.ndarray | None = None) -> np.ndarray:
    """q (..., n_q) minimising sum |markers(q) - markers|^2 over every endplate marker (Gauss-
    Newton with a Levenberg-Marquardt floor, each bend clipped to theta_max), from q0 (default:
    `bends_from_markers`). Markers (..., N + 1, 3) without NaN."""
    markers = np.asarray(markers, dtype=float)
    q = bends_from_markers(model, markers) if q0 is None else np.array(q0, dtype=float)
    batch = markers.shape[:-2]
    q = np.broadcast_to(q, (*batch, model.n_q)).reshape(-1, model.n_q).copy()
    seen = markers[..., 1:, :].reshape(len(q), -1)
    eye = np.eye(model.n_q)
    for _ in range(FIT_ITERATIONS):
        m, J = marker_jacobian(model, q)
        e = m[:, 1:, :].reshape(len(q), -1) - seen
        J = J[:, 1:, :, :].reshape(len(q), -1, model.n_q)
        A = np.einsum("bki,bkj->bij", J, J)
        A = A + FIT_DAMPING * np.trace(A, axis1=1, axis2=2)[:, None, None] * eye
        step = -np.linalg.solve(A, np.einsum("bki,bk->bi", J, e)[..., None])[..., 0]
        q = _clip(model, q + step)
        if np.max(np.abs(step)) <= FIT_TOLERANCE:
            break
    return q.reshape(*batch, model.n_q)


def _clip(model: ArmModel, q: np.ndarray) -> np.ndarray:
    """Every segment's bend scaled back onto theta_max where beyond it."""
    full = model.full(q)
    theta = np.linalg.norm(full, axis=-1, keepdims=True)
    scale = np.minimum(1.0, model.theta_max / np.maximum(theta, 1e-300))
    return model.reduce(full * scale)
