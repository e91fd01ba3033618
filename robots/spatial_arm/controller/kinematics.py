"""The spatial arm's kinematics, exactly ArmBody's (fmus/ArmBody/README.md, "Kinematics").

Segment i bends by (u, v) = (theta_x, theta_y) = theta (cos gamma, sin gamma); its transform is
`Rz(gamma) Tz(L_p) Ry(theta/2) Tz(chord) Ry(theta/2) Tz(L_p) Rz(-gamma)`, written as the FMU
writes it, without gamma (undefined at theta = 0): with T = u^2 + v^2 and

    a(W) = sin(sqrt W) / sqrt W,   b(W) = (1 - cos(sqrt W)) / W,

the point at the fraction xi of the arc is r = (F u, F v, G) in the segment's base frame, F = L
xi^2 b(xi^2 T), G = L_p + L xi a(xi^2 T); the tip frame's origin (the endplate, after the distal
end piece) has F = L b + L_p a, G = 2 L_p + L a - L_p T b, and the tip frame is turned by R = I +
a K + b K^2, K = [phi]x, phi = (-v, u, 0). a and b (and their derivatives in W) take their
Taylor series below W = 1 (ten terms: truncation below 1e-19) and closed forms above, so there is
neither 0/0 nor cancellation, and every function here is complex-analytic in q (complex-step
differentiation through them is exact to rounding).

Jacobians are analytic: a point p beyond segment s moves with s's coordinate a by
R_s (dr_tip/da + dR_loc/da y), y = R_{s+1}^T (p - P_{s+1}) its position in the next segment's
base frame, and a point of segment s itself by R_s dr/da.

Shapes: q is (..., n_q), any leading batch shape (model.py: coordinates); the functions are
vectorised over it. Markers are the base origin and every endplate, (..., N + 1, 3).
"""

from __future__ import annotations

from dataclasses import dataclass
from math import factorial

import numpy as np

from robots.spatial_arm.controller.model import ArmModel

SERIES_BELOW = 1.0  # W below which a, b take their series
N_TERMS = 10  # series terms: the first left out is below 1 / 21! ~ 2e-20 at W = 1
# coefficients of a, b and their first derivatives in W, ascending powers
_A = np.array([(-1.0) ** j / factorial(2 * j + 1) for j in range(N_TERMS + 1)])
_B = np.array([(-1.0) ** j / factorial(2 * j + 2) for j in range(N_TERMS + 1)])
_DA = np.array([(j + 1) * _A[j + 1] for j in range(N_TERMS)])
_DB = np.array([(j + 1) * _B[j + 1] for j in range(N_TERMS)])


def _horner(coefficients: np.ndarray, W: np.ndarray) -> np.ndarray:
    out = np.zeros_like(W) + coefficients[-1]
    for c in coefficients[-2::-1]:
        out = out * W + c
    return out


def bend_functions(W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """a(W), a'(W), b(W), b'(W) (derivatives in W), for real or complex W >= 0 (real part)."""
    W = np.asarray(W)
    series = W.real < SERIES_BELOW
    Ws = np.where(series, W, 0.0)
    Wc = np.where(series, 1.0, W)
    t = np.sqrt(Wc)
    sn, cs = np.sin(t), np.cos(t)
    closed = (
        sn / t,
        (t * cs - sn) / (2.0 * t * Wc),
        (1.0 - cs) / Wc,
        (0.5 * t * sn - 1.0 + cs) / (Wc * Wc),
    )
    coefficients = (_A[:N_TERMS], _DA, _B[:N_TERMS], _DB)
    a, da, b, db = (
        np.where(series, _horner(c, Ws), f) for c, f in zip(coefficients, closed, strict=True)
    )
    return a, da, b, db


def _point(F: tuple, G: tuple, u: np.ndarray, v: np.ndarray) -> tuple:
    """r = (F u, F v, G) with F = F(T), G = G(T), T = u^2 + v^2, and dr/du, dr/dv (each
    shape (..., 3)); F, G are (value, derivative in T)."""
    F0, F1 = F
    G0, G1 = G
    r = np.stack([F0 * u, F0 * v, G0 + 0.0 * u], axis=-1)
    du = np.stack([F0 + 2.0 * u * u * F1, 2.0 * u * v * F1, 2.0 * u * G1], axis=-1)
    dv = np.stack([2.0 * u * v * F1, F0 + 2.0 * v * v * F1, 2.0 * v * G1], axis=-1)
    return r, du, dv


def arc_point(L: np.ndarray, L_p: np.ndarray, xi: np.ndarray, u: np.ndarray, v: np.ndarray):
    """The point at the fraction xi of the arc in its segment's base frame and its derivatives
    in u and v (arrays broadcasting together)."""
    x2 = xi * xi
    a, da, b, db = bend_functions(x2 * (u * u + v * v))
    F = (L * x2 * b, L * x2 * x2 * db)
    G = (L_p + L * xi * a, L * xi * x2 * da)
    return _point(F, G, u, v)


def tip_point(L: np.ndarray, L_p: np.ndarray, u: np.ndarray, v: np.ndarray):
    """The tip frame's origin (the endplate) in the segment's base frame, its derivatives, and
    the bend functions at T (for the tip's rotation)."""
    T = u * u + v * v
    fs = bend_functions(T)
    a, da, b, db = fs
    F = (L * b + L_p * a, L * db + L_p * da)
    G = (2.0 * L_p + L * a - L_p * T * b, L * da - L_p * (b + T * db))
    return (*_point(F, G, u, v), fs)


def tip_rotation(u: np.ndarray, v: np.ndarray, fs: tuple) -> tuple:
    """R = I + a K + b K^2 (phi = (-v, u, 0)) and its derivatives in u and v, (..., 3, 3)."""
    a, da, b, db = fs
    T = u * u + v * v
    one = np.ones_like(T)
    R = _matrix(
        [
            [one - b * u * u, -b * u * v, a * u],
            [-b * u * v, one - b * v * v, a * v],
            [-a * u, -a * v, one - b * T],
        ]
    )
    out = [R]
    for w, z, sign in ((u, v, 0), (v, u, 1)):
        # derivative in w (u or v), z the other coordinate: a_w = 2 w a', b_w = 2 w b'
        aw, bw = 2.0 * w * da, 2.0 * w * db
        ww = -(bw * w * w + 2.0 * b * w)  # d(-b w^2)/dw
        zz = -bw * z * z  # d(-b z^2)/dw
        wz = -(bw * w * z + b * z)  # d(-b w z)/dw
        aw_w, aw_z = aw * w + a, aw * z  # d(a w)/dw, d(a z)/dw
        corner = -(bw * T + 2.0 * w * b)
        if sign == 0:  # w = u, z = v
            rows = [[ww, wz, aw_w], [wz, zz, aw_z], [-aw_w, -aw_z, corner]]
        else:  # w = v, z = u
            rows = [[zz, wz, aw_z], [wz, ww, aw_w], [-aw_z, -aw_w, corner]]
        out.append(_matrix(rows))
    return tuple(out)


def _matrix(rows: list) -> np.ndarray:
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


@dataclass(frozen=True)
class Chain:
    """The arm at a batch of configurations (leading shape B... of q): per segment s its base
    frame R[..., s], P[..., s] (index N: the last tip frame), its tip point in its own frame and
    the derivatives of that point and of its tip rotation in (u, v)."""

    R: np.ndarray  # (..., N + 1, 3, 3)
    P: np.ndarray  # (..., N + 1, 3)
    u: np.ndarray  # (..., N)
    v: np.ndarray
    tip_d: np.ndarray  # (..., N, 2, 3): dr_tip/du, dr_tip/dv in the segment's base frame
    rot_d: np.ndarray  # (..., N, 2, 3, 3): dR_loc/du, dR_loc/dv


def chain(model: ArmModel, q: np.ndarray) -> Chain:
    """Walk from the base: every segment's base frame in the base frame, at q (..., n_q)."""
    uv = model.full(q)
    u, v = uv[..., 0], uv[..., 1]
    L, L_p = np.asarray(model.L), np.asarray(model.L_p)
    r, du, dv, fs = tip_point(L, L_p, u, v)
    rot, rot_u, rot_v = tip_rotation(u, v, fs)
    batch, n = u.shape[:-1], model.n_segments
    R = np.empty((*batch, n + 1, 3, 3), dtype=r.dtype)
    P = np.empty((*batch, n + 1, 3), dtype=r.dtype)
    R[..., 0, :, :] = np.eye(3)
    P[..., 0, :] = 0.0
    for s in range(n):
        P[..., s + 1, :] = P[..., s, :] + np.einsum(
            "...ij,...j->...i", R[..., s, :, :], r[..., s, :]
        )
        R[..., s + 1, :, :] = R[..., s, :, :] @ rot[..., s, :, :]
    return Chain(
        R=R,
        P=P,
        u=u,
        v=v,
        tip_d=np.stack([du, dv], axis=-2),
        rot_d=np.stack([rot_u, rot_v], axis=-3),
    )


def frames(model: ArmModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every endplate's frame (R, p) in the base frame, index 0 the base itself: shapes
    (..., N + 1, 3, 3) and (..., N + 1, 3)."""
    c = chain(model, q)
    return c.R, c.P


def markers(model: ArmModel, q: np.ndarray) -> np.ndarray:
    """The base origin and every endplate's origin, (..., N + 1, 3)."""
    return chain(model, q).P


def tip(model: ArmModel, q: np.ndarray) -> np.ndarray:
    """The last endplate's origin, (..., 3)."""
    return chain(model, q).P[..., -1, :]


# ------------------------------------------------------------------ points along the arm


@dataclass(frozen=True)
class Stations:
    """Points along the arm: segment index, fraction of its arc (NaN: its endplate), and the
    arc length from the base along the backbone (end pieces included)."""

    segment: np.ndarray  # (P,) int
    xi: np.ndarray  # (P,) float, NaN for an endplate
    arc_length: np.ndarray  # (P,) [m]

    @property
    def is_tip(self) -> np.ndarray:
        return np.isnan(self.xi)


def stations(model: ArmModel, per_segment: int = 8, endplates: bool = True) -> Stations:
    """`per_segment` arc points per segment at xi = 0 ... 1 (both ends of the arc) and, with
    `endplates`, every endplate after its segment's arc."""
    seg, xi, s = [], [], []
    start = 0.0
    fractions = np.linspace(0.0, 1.0, per_segment) if per_segment > 1 else np.array([1.0])
    for i in range(model.n_segments):
        L, L_p = model.L[i], model.L_p[i]
        for f in fractions:
            seg.append(i)
            xi.append(f)
            s.append(start + L_p + f * L)
        if endplates:
            seg.append(i)
            xi.append(np.nan)
            s.append(start + L + 2.0 * L_p)
        start += L + 2.0 * L_p
    return Stations(np.asarray(seg, dtype=int), np.asarray(xi), np.asarray(s))


def points(
    model: ArmModel, q: np.ndarray, where: Stations, jacobian: bool = False
) -> tuple[np.ndarray, np.ndarray | None]:
    """The stations' positions in the base frame, (..., P, 3), and with `jacobian` their
    derivatives in q, (..., P, 3, n_q)."""
    c = chain(model, q)
    seg, tip_mask = where.segment, where.is_tip
    xi = np.where(tip_mask, 1.0, where.xi)
    L, L_p = np.asarray(model.L)[seg], np.asarray(model.L_p)[seg]
    u, v = c.u[..., seg], c.v[..., seg]
    r_arc, du_arc, dv_arc = arc_point(L, L_p, xi, u, v)
    r_tip, du_tip, dv_tip, _ = tip_point(L, L_p, u, v)
    pick = tip_mask[:, None]
    r = np.where(pick, r_tip, r_arc)
    R_seg, P_seg = c.R[..., seg, :, :], c.P[..., seg, :]
    p = P_seg + np.einsum("...ij,...j->...i", R_seg, r)
    if not jacobian:
        return p, None
    own = np.stack([np.where(pick, du_tip, du_arc), np.where(pick, dv_tip, dv_arc)], axis=-1)
    return p, _jacobian(model, c, p, seg, np.einsum("...ij,...ja->...ia", R_seg, own))


def _jacobian(
    model: ArmModel, c: Chain, p: np.ndarray, seg: np.ndarray, own: np.ndarray
) -> np.ndarray:
    """dp/dq of points p (..., P, 3) of segments seg (P,), own (..., P, 3, 2) their
    derivatives in their own segment's coordinates (base frame)."""
    n = model.n_segments
    R_s = c.R[..., :n, :, :]
    # columns of every segment s on every point: R_s dr_tip/da + R_s dR/da R_{s+1}^T (p - P_s+1)
    lin = np.einsum("...sij,...saj->...sai", R_s, c.tip_d)
    turn = np.einsum("...sij,...sajk,...slk->...sail", R_s, c.rot_d, c.R[..., 1:, :, :])
    rel = p[..., None, :, :] - c.P[..., 1:, None, :]  # (..., s, P, 3)
    cols = lin[..., None, :, :] + np.einsum("...sail,...spl->...spai", turn, rel)
    before = np.arange(n)[:, None] < seg[None, :]  # (s, P)
    cols = np.where(before[:, :, None, None], cols, 0.0)
    mine = np.arange(n)[:, None] == seg[None, :]
    cols = cols + np.where(mine[:, :, None, None], np.moveaxis(own, -1, -2)[..., None, :, :, :], 0)
    # (..., s, P, a, 3) -> (..., P, 3, s, a) -> (..., P, 3, n_q)
    full = np.moveaxis(cols, (-4, -3, -2, -1), (-2, -4, -1, -3))
    return model.reduce(full)


def marker_jacobian(model: ArmModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """markers(q) (..., N + 1, 3) and their derivatives in q (..., N + 1, 3, n_q) (the base
    origin's row is zero)."""
    where = Stations(
        np.arange(model.n_segments), np.full(model.n_segments, np.nan), np.zeros(model.n_segments)
    )
    p, J = points(model, q, where, jacobian=True)
    assert J is not None
    batch = p.shape[:-2]
    origin = np.zeros((*batch, 1, 3), dtype=p.dtype)
    return np.concatenate([origin, p], axis=-2), np.concatenate(
        [np.zeros((*batch, 1, 3, model.n_q), dtype=J.dtype), J], axis=-3
    )


def tip_jacobian(model: ArmModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tip (..., 3) and its Jacobian (..., 3, n_q)."""
    m, J = marker_jacobian(model, q)
    return m[..., -1, :], J[..., -1, :, :]


def backbone(model: ArmModel, q: np.ndarray, per_segment: int = 16) -> np.ndarray:
    """The backbone as a polyline for drawing: the base origin, then per segment its arc at
    `per_segment` points (the end pieces are the straight lines to and from them) and its
    endplate: (..., 1 + N (per_segment + 1), 3)."""
    p, _ = points(model, q, stations(model, per_segment))
    origin = np.zeros((*p.shape[:-2], 1, 3), dtype=p.dtype)
    return np.concatenate([origin, p], axis=-2)
