"""Planar piecewise-constant-curvature (PCC) kinematics (PHYSICS.md section 3).

Shared truth between the plant (the camera computes marker positions from the true curvatures)
and the controller (which inverts markers back to curvatures). A planar segment of arc length L
and curvature k, starting at pose (x0, y0, th0), ends at
    x = x0 + (sin(th0 + k L) - sin th0) / k,  y = y0 - (cos(th0 + k L) - cos th0) / k,
    th = th0 + k L,
computed in the equivalent chord form (see `segment_end`), with the series limit of sin(u)/u for
|k| < 1e-6. Markers sit on the base and on each segment's end.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

SMALL_CURVATURE = 1e-6


def segment_end(
    pose: tuple[float, float, float], kappa: float, length: float
) -> tuple[float, float, float]:
    """End pose (x, y, heading) of a constant-curvature segment starting at `pose`."""
    x0, y0, th0 = pose
    half = 0.5 * kappa * length
    # the same end point written as a chord of length L sinc(kL/2) along th0 + kL/2: it has no
    # cancellation, so it is exact to rounding for every curvature; below SMALL_CURVATURE the
    # sinc takes its series
    sinc = 1.0 - half * half / 6.0 if abs(kappa) < SMALL_CURVATURE else math.sin(half) / half
    chord = length * sinc
    direction = th0 + half
    return x0 + chord * math.cos(direction), y0 + chord * math.sin(direction), th0 + 2.0 * half


def forward(
    kappas: Sequence[float], lengths: Sequence[float], base: tuple[float, float, float]
) -> np.ndarray:
    """Poses of the base and of every segment end, shape (N + 1, 3): x [m], y [m], heading [rad]."""
    poses = [base]
    for kappa, length in zip(kappas, lengths, strict=True):
        poses.append(segment_end(poses[-1], float(kappa), float(length)))
    return np.array(poses)


def markers(
    kappas: Sequence[float], lengths: Sequence[float], base: tuple[float, float, float]
) -> np.ndarray:
    """Marker positions (base, then each segment end), shape (N + 1, 2) [m]."""
    return forward(kappas, lengths, base)[:, :2]


def curvatures_from_markers(
    points: np.ndarray, lengths: Sequence[float], base_heading: float
) -> np.ndarray:
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
