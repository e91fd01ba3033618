"""Planar piecewise-constant-curvature (PCC) kinematics.

Shared truth between the plant (the camera computes marker positions from the true curvatures)
and the controller (which inverts markers back to curvatures). A planar segment of arc length L
and curvature k, starting at pose (x0, y0, th0), ends at
    x = x0 + (sin(th0 + k L) - sin th0) / k,  y = y0 - (cos(th0 + k L) - cos th0) / k,
    th = th0 + k L,
computed in the equivalent chord form (see `segment_end`), with the series limit of sin(u)/u for
|k| < 1e-6. Markers sit on the base and on each segment's end.

Along the arm, the pose at arc length s is that of a partial segment (the same chord form with
the partial length), and the task-space Jacobians are closed forms: bending segment i by d kappa
turns everything distal to it by L_i d kappa about the end of segment i, and moves that end by the
derivative of its own chord. Both are exact to rounding for every curvature, including zero
(series of sinc and its derivative below a small bend angle).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

# curvatures, lengths: any sequence of floats, numpy arrays included
Floats = Sequence[float] | np.ndarray

SMALL_CURVATURE = 1e-6
# below this half bend angle [rad] d sinc/dh takes its series: (h cos h - sin h) / h^2 loses
# 3 eps / h^2 of relative accuracy to cancellation, the three-term series errs by h^7 / 45360
SMALL_HALF_ANGLE = 1e-2
# an arc length this fraction of the arm's length beyond an end or a joint is rounding
ARC_TOLERANCE = 1e-12


def segment_end(
    pose: tuple[float, float, float], kappa: float, length: float
) -> tuple[float, float, float]:
    """End pose (x, y, heading) of a constant-curvature segment starting at `pose`."""
    x0, y0, th0 = pose
    half = 0.5 * kappa * length
    # the same end point written as a chord of length L sinc(kL/2) along th0 + kL/2: it has no
    # cancellation, so it is exact to rounding for every curvature; below SMALL_CURVATURE the
    # sinc takes its series (as it must for a zero length: pose_at's point at a segment start)
    small = abs(kappa) < SMALL_CURVATURE or half == 0.0
    sinc = 1.0 - half * half / 6.0 if small else math.sin(half) / half
    chord = length * sinc
    direction = th0 + half
    return x0 + chord * math.cos(direction), y0 + chord * math.sin(direction), th0 + 2.0 * half


def forward(kappas: Floats, lengths: Floats, base: tuple[float, float, float]) -> np.ndarray:
    """Poses of the base and of every segment end, shape (N + 1, 3): x [m], y [m], heading [rad]."""
    poses = [base]
    for kappa, length in zip(kappas, lengths, strict=True):
        poses.append(segment_end(poses[-1], float(kappa), float(length)))
    return np.array(poses)


def markers(kappas: Floats, lengths: Floats, base: tuple[float, float, float]) -> np.ndarray:
    """Marker positions (base, then each segment end), shape (N + 1, 2) [m]."""
    return forward(kappas, lengths, base)[:, :2]


def curvatures_from_markers(points: np.ndarray, lengths: Floats, base_heading: float) -> np.ndarray:
    """Per-segment curvature from consecutive marker positions (the chord-angle inverse).

    For a circular arc the chord direction alpha is the mean of start and end headings, so
    kappa = 2 (alpha - th0) / L and the next start heading is th0 + kappa L.

    Parameters
    ----------
    points
        Marker positions, shape (N + 1, 2): the base marker, then each segment end [m].
    lengths
        Segment arc lengths, shape (N,) [m].
    base_heading
        Heading of the first segment's tangent at the base [rad].
    """
    points = np.asarray(points, dtype=float)
    kappas = np.empty(len(lengths))
    heading = base_heading
    for i, length in enumerate(lengths):
        dx, dy = points[i + 1] - points[i]
        alpha = math.atan2(dy, dx)
        # wrap the half-angle into (-pi, pi] so that a chord behind the tangent is not a 2 pi jump
        half = math.remainder(alpha - heading, 2.0 * math.pi)
        kappas[i] = 2.0 * half / length
        heading += kappas[i] * length
    return kappas


def _segment_at(lengths: Floats, s: float) -> tuple[int, float]:
    """Index of the segment holding arc length `s` and the length of it up to `s` [m].

    A point on a joint belongs to the proximal segment (its whole length), so s = 0 is the
    zero-length start of segment 0 and s = sum(lengths) the whole last segment. Rounding-sized
    excursions (ARC_TOLERANCE of the arm's length) snap to the nearest end or joint, so that an
    s summed in another order still lands on the joint."""
    total = math.fsum(lengths)
    tolerance = ARC_TOLERANCE * total
    if not -tolerance <= s <= total + tolerance:
        raise ValueError(f"arc length s = {s!r} m is outside the arm [0, {total!r}]")
    start = 0.0
    for i, length in enumerate(lengths):
        length = float(length)
        if s <= start + length + tolerance or i == len(lengths) - 1:
            partial = s - start
            if abs(partial - length) <= tolerance or partial > length:
                return i, length
            return i, max(partial, 0.0)
        start += length
    raise ValueError(f"arc length s = {s!r} m: the arm has no segments")


def pose_at(
    kappas: Floats, lengths: Floats, base: tuple[float, float, float], s: float
) -> tuple[float, float, float]:
    """Pose (x [m], y [m], heading [rad]) of the backbone at arc length `s` [m] from the base.

    Raises ValueError naming `s` when it lies outside [0, sum(lengths)]. At s = the end of
    segment i it equals ``forward(...)[i + 1]`` exactly."""
    if len(kappas) != len(lengths):
        raise ValueError(f"{len(kappas)} curvatures for {len(lengths)} segment lengths")
    index, partial = _segment_at(lengths, s)
    start = forward(kappas[:index], lengths[:index], base)[-1]
    if partial == lengths[index]:
        # the whole segment: the same arithmetic as forward(), so joints match bit for bit
        return segment_end(tuple(start), float(kappas[index]), float(lengths[index]))
    return segment_end(tuple(start), float(kappas[index]), partial)


def backbone(
    kappas: Floats,
    lengths: Floats,
    base: tuple[float, float, float],
    per_segment: int = 8,
) -> np.ndarray:
    """Poses sampled along the arm, shape (N per_segment + 1, 3): x [m], y [m], heading [rad].

    Row 0 is the base, row i per_segment the end of segment i (equal to ``forward``); each
    segment is sampled at equal arc-length steps L_i / per_segment."""
    if per_segment < 1:
        raise ValueError(f"per_segment = {per_segment} must be at least 1")
    joints = forward(kappas, lengths, base)
    rows = [joints[0]]
    for i, (kappa, length) in enumerate(zip(kappas, lengths, strict=True)):
        start = tuple(joints[i])
        for j in range(1, per_segment):
            rows.append(segment_end(start, float(kappa), float(length) * j / per_segment))
        rows.append(joints[i + 1])
    return np.array(rows, dtype=float)


def _chord_derivative(heading: float, kappa: float, length: float) -> tuple[float, float]:
    """d/d kappa of the chord (end minus start) of an arc of `length` starting at `heading`
    [m^2]: with h = kappa L / 2 the chord is L sinc(h) e(heading + h), so its derivative is
    (L^2 / 2) (sinc'(h) e + sinc(h) e_perp), e_perp the left normal."""
    half = 0.5 * kappa * length
    if abs(half) < SMALL_HALF_ANGLE:
        h2 = half * half
        sinc = 1.0 - h2 / 6.0 * (1.0 - h2 / 20.0)
        dsinc = -half / 3.0 * (1.0 - h2 / 10.0 * (1.0 - h2 / 28.0))
    else:
        sinc = math.sin(half) / half
        dsinc = (half * math.cos(half) - math.sin(half)) / (half * half)
    direction = heading + half
    c, s = math.cos(direction), math.sin(direction)
    scale = 0.5 * length * length
    return scale * (dsinc * c - sinc * s), scale * (dsinc * s + sinc * c)


def _columns(
    kappas: Floats,
    lengths: Floats,
    joints: np.ndarray,
    point: Sequence[float],
    index: int,
    partial: float,
) -> np.ndarray:
    """Jacobian columns of `point`, on segment `index` at `partial` length, given the joint
    poses up to that segment's start (see `point_jacobian`)."""
    jacobian = np.zeros((3, len(kappas)))
    for i in range(index + 1):
        length = float(lengths[i]) if i < index else partial
        end = joints[i + 1] if i < index else point
        dx, dy = _chord_derivative(float(joints[i][2]), float(kappas[i]), length)
        # the distal chain turns by L_i d kappa about this segment's end
        jacobian[0, i] = dx - length * (point[1] - end[1])
        jacobian[1, i] = dy + length * (point[0] - end[0])
        jacobian[2, i] = length
    return jacobian


def point_jacobian(
    kappas: Floats, lengths: Floats, base: tuple[float, float, float], s: float
) -> np.ndarray:
    """Jacobian of the pose at arc length `s` with respect to the curvatures, shape (3, N).

    Rows d x, d y [m per 1/m] and d heading [rad per 1/m]. Column i (segment i before the
    point's segment j): d heading = L_i, d position = the derivative of segment i's chord plus
    L_i times the left normal of (point - end of segment i); column j: the same with the partial
    length; distal columns are zero."""
    if len(kappas) != len(lengths):
        raise ValueError(f"{len(kappas)} curvatures for {len(lengths)} segment lengths")
    index, partial = _segment_at(lengths, s)
    joints = forward(kappas[:index], lengths[:index], base)
    point = segment_end(tuple(joints[-1]), float(kappas[index]), partial)
    return _columns(kappas, lengths, joints, point, index, partial)


def tip_jacobian(kappas: Floats, lengths: Floats, base: tuple[float, float, float]) -> np.ndarray:
    """Jacobian of the tip pose (x, y, heading) with respect to the curvatures, shape (3, N):
    rows in m per 1/m (position) and rad per 1/m (heading); see `point_jacobian`."""
    return tip_derivatives(kappas, lengths, base)[1]


# coefficients i^n / (n + 1)! of the power series of g(a) = (exp(i a) - 1) / (i a)
_SERIES = tuple(1j**n / math.factorial(n + 1) for n in range(18))
SERIES_ANGLE = 0.5  # [rad] below it g'' takes its series (the closed form loses eps / a^2)


def _arc_curvature(angle: float) -> complex:
    """g''(a) for g(a) = (exp(i a) - 1) / (i a), the chord of a unit-length arc of bend angle a
    as a complex number relative to its start heading.

    From i a g = exp(i a) - 1: g' = (exp(i a) - g) / a and g'' = (i exp(i a) - 2 g') / a, which
    cancel at small angles, where the power series g = sum (i a)^n / (n + 1)! is used instead
    (below 0.5 rad its 18 terms are exact to rounding)."""
    if abs(angle) < SERIES_ANGLE:
        d2g, power = 0j, 1.0  # power = angle^(n - 2)
        for n in range(2, len(_SERIES)):
            d2g += n * (n - 1) * _SERIES[n] * power
            power *= angle
        return d2g
    turn = complex(math.cos(angle), math.sin(angle))
    g = (turn - 1.0) / (1j * angle)
    dg = (turn - g) / angle
    return (1j * turn - 2.0 * dg) / angle


def tip_derivatives(
    kappas: Floats, lengths: Floats, base: tuple[float, float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tip pose, its Jacobian and its position Hessian with respect to the curvatures, from one
    pass along the arm.

    Returns
    -------
    tip, jacobian, hessian
        Tip pose (x [m], y [m], heading [rad]); Jacobian, shape (3, N), as `tip_jacobian`;
        Hessian of the tip position, shape (2, N, N) [m per (1/m)^2] (the heading is linear in
        the curvatures).

    Notes
    -----
    In bend angles theta_i = kappa_i L_i, with the tip p as a complex number and J_k its column
    k: d2p / d theta_j d theta_k = i J_k for j < k (bending j turns the distal bend's effect by
    90 degrees), and L_j g''(theta_j) exp(i phi_j) - (p - p_{j+1}) on the diagonal (phi_j the
    start heading of segment j, g as in `_arc_curvature`); in curvatures, times L_j L_k.
    """
    if len(kappas) != len(lengths):
        raise ValueError(f"{len(kappas)} curvatures for {len(lengths)} segment lengths")
    n = len(lengths)
    joints = forward(kappas, lengths, base)
    tip = joints[-1]
    if n == 0:
        return tip, np.zeros((3, 0)), np.zeros((2, 0, 0))
    jacobian = _columns(kappas, lengths, joints, tip, n - 1, float(lengths[-1]))
    lengths_ = np.asarray(lengths, dtype=float)
    # columns of the bend-angle Jacobian as complex numbers
    columns = (jacobian[0] + 1j * jacobian[1]) / lengths_
    point = complex(tip[0], tip[1])
    hessian = np.empty((n, n), dtype=complex)
    for j in range(n):
        start = complex(math.cos(joints[j][2]), math.sin(joints[j][2]))
        end = complex(joints[j + 1][0], joints[j + 1][1])
        curvature = _arc_curvature(float(kappas[j]) * float(lengths[j]))
        hessian[j, j] = lengths_[j] * curvature * start - (point - end)
        hessian[j, j + 1 :] = hessian[j + 1 :, j] = 1j * columns[j + 1 :]
    hessian *= np.outer(lengths_, lengths_)
    return tip, jacobian, np.stack((hessian.real, hessian.imag))


def tip_hessian(kappas: Floats, lengths: Floats, base: tuple[float, float, float]) -> np.ndarray:
    """Second derivatives of the tip position with respect to the curvatures, shape (2, N, N)
    [m per (1/m)^2]; see `tip_derivatives`."""
    return tip_derivatives(kappas, lengths, base)[2]


# Gauss-Legendre nodes and weights (summing to 1) on [0, 1]: 4 points, as the ArmBody FMU
# lumps each arc's mass (exact for the straight arm, whose integrands are polynomials of degree 4)
_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(4)
MASS_NODES = tuple(float(v) for v in 0.5 * (_NODES + 1.0))
MASS_WEIGHTS = tuple(float(v) for v in 0.5 * _WEIGHTS)


def mass_matrix(kappas: Floats, lengths: Floats, masses: Floats) -> np.ndarray:
    """The planar arm's mass matrix on its bend angles theta_i = kappa_i L_i [kg m^2], shape
    (N, N): M = sum over the arm's mass of J' J, J the point's Jacobian on the bend angles,
    each segment's mass uniform along its arc, lumped at MASS_NODES (the ArmBody FMU's
    particle form without end pieces or endplates). The base's pose does not enter."""
    n = len(kappas)
    if not len(lengths) == len(masses) == n:
        raise ValueError(f"{n} curvatures, {len(lengths)} lengths and {len(masses)} masses")
    base = (0.0, 0.0, 0.0)
    joints = forward(kappas, lengths, base)
    per_angle = 1.0 / np.asarray(lengths, dtype=float)
    M = np.zeros((n, n))
    for index in range(n):
        length = float(lengths[index])
        for xi, weight in zip(MASS_NODES, MASS_WEIGHTS, strict=True):
            partial = xi * length
            point = segment_end(tuple(joints[index]), float(kappas[index]), partial)
            J = _columns(kappas, lengths, joints, point, index, partial)[:2] * per_angle
            M += float(masses[index]) * weight * (J.T @ J)
    return M
