"""How far an object on the table is from the planar arm and its open soft gripper, in one
configuration and along the straight curvature interpolation between two (issue 12): what keeps
grasp-and-place planning (robots.planar_arm.controller.grasp_planner) from touching the object.

The arm's backbone is a chain of capsules (radius width / 2) and each finger a capsule (radius
finger_width / 2) along its arc. The clearance is a guaranteed bound, not a sampled hope: arcs
are sampled as polylines less their sagitta, and along an interpolation the samples are spaced
so that no body point moves more than SWEEP_TOLERANCE between them (a Lipschitz bound on the
kinematics), and SWEEP_TOLERANCE / 2 is taken off.

Invariant: every clearance returned is a lower bound of the true one; every function is
deterministic.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from robots.planar_arm.controller.gripper import GripperGeometry, finger_points

Floats = Sequence[float] | np.ndarray
Pose = tuple[float, float, float]

ARM_WIDTH = 0.02  # [m] the planar arm's "rectangular" segments: backbone capsule radius 0.01 m
BODY_SAMPLES = 16  # polyline points per segment and per finger (their sagitta is subtracted)
SWEEP_TOLERANCE = 5e-4  # [m] largest move of any body point between two checked configurations


def _poses(kappas: np.ndarray, lengths: np.ndarray, base: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Backbone polylines and tip poses of many configurations at once.

    The closed forms of `kinematics.segment_end` (the chord form), vectorised over
    configurations: points at s = L_i j / BODY_SAMPLES on every segment, base first.

    Returns
    -------
    points, tips
        Shape (m, N BODY_SAMPLES + 1, 2) [m] and (m, 3) (x, y, heading).
    """
    theta = kappas * lengths  # (m, N)
    m, n = theta.shape
    heading = base[2] + np.concatenate((np.zeros((m, 1)), np.cumsum(theta, axis=1)), axis=1)
    half = 0.5 * theta
    chord = lengths * np.sinc(half / math.pi)
    direction = heading[:, :-1] + half
    steps = np.stack((chord * np.cos(direction), chord * np.sin(direction)), axis=2)
    joints = np.concatenate(
        (np.broadcast_to(np.array(base[:2]), (m, 1, 2)), np.array(base[:2]) + np.cumsum(steps, 1)),
        axis=1,
    )
    fraction = np.arange(1, BODY_SAMPLES + 1) / BODY_SAMPLES
    partial = half[:, :, None] * fraction  # (m, N, samples)
    pchord = lengths[:, None] * fraction * np.sinc(partial / math.pi)
    pdirection = heading[:, :-1, None] + partial
    inner = joints[:, :-1, None, :] + np.stack(
        (pchord * np.cos(pdirection), pchord * np.sin(pdirection)), axis=3
    )
    points = np.concatenate((joints[:, :1], inner.reshape(m, n * BODY_SAMPLES, 2)), axis=1)
    tips = np.concatenate((joints[:, -1], heading[:, -1:]), axis=1)
    return points, tips


def _polyline_distance(
    points: np.ndarray, centre: np.ndarray, sag: np.ndarray | float
) -> np.ndarray:
    """Distance [m] from `centre` to each polyline (points shape (m, k, 2)), each piece's
    distance lowered by its sagitta `sag` (shape broadcasting to (m, k - 1)), so that it bounds
    the distance to the arcs the pieces are chords of."""
    a, b = points[:, :-1], points[:, 1:]
    ab = b - a
    t = np.clip(np.sum((centre - a) * ab, axis=2) / np.sum(ab * ab, axis=2), 0.0, 1.0)
    nearest = a + t[..., None] * ab
    return np.min(np.linalg.norm(centre - nearest, axis=2) - sag, axis=1)


def _clearances(
    kappas: np.ndarray,
    centre: Floats,
    object_radius: float,
    lengths: np.ndarray,
    base: Pose,
    geometry: GripperGeometry,
    theta: float,
    width: float,
) -> np.ndarray:
    """Clearance [m] of the object's disk from the fingers (bend angle `theta`) and the backbone
    capsules of each configuration (kappas shape (m, N)): negative where they overlap."""
    kappas = np.atleast_2d(kappas)
    c = np.asarray(centre, dtype=float)
    points, tips = _poses(kappas, lengths, base)
    # a chord of length s on an arc of curvature k lies within s^2 |k| / 8 of the arc
    sag = np.repeat((lengths / BODY_SAMPLES) ** 2 * np.abs(kappas) / 8.0, BODY_SAMPLES, axis=1)
    body = _polyline_distance(points, c, sag) - 0.5 * width
    finger_sag = (geometry.finger_length / BODY_SAMPLES) * abs(theta) / BODY_SAMPLES / 8.0
    cos, sin = np.cos(tips[:, 2])[:, None], np.sin(tips[:, 2])[:, None]
    nearest = body
    for local in finger_points(geometry, (0.0, 0.0, 0.0), theta, BODY_SAMPLES):
        # the fingers are rigid in the tip's frame: rotate and translate their local shape
        world = np.stack(
            (
                tips[:, :1] + cos * local[:, 0] - sin * local[:, 1],
                tips[:, 1:2] + sin * local[:, 0] + cos * local[:, 1],
            ),
            axis=2,
        )
        finger = _polyline_distance(world, c, finger_sag) - 0.5 * geometry.finger_width
        nearest = np.minimum(nearest, finger)
    return np.asarray(nearest - object_radius)


def clearance(
    kappas: Floats,
    centre: tuple[float, float],
    object_radius: float,
    lengths: Floats,
    base: Pose,
    geometry: GripperGeometry,
    theta: float,
    *,
    width: float = ARM_WIDTH,
) -> float:
    """Lower bound of the clearance [m] between an object's disk (centre [m], radius [m]) and
    the arm in configuration `kappas` [1/m]: its backbone capsules (radius width / 2) and its
    fingers at bend angle `theta` [rad] (capsules of radius finger_width / 2); negative where
    they overlap. Exact to within the sagitta of BODY_SAMPLES pieces, which is subtracted."""
    lengths_ = np.asarray(lengths, dtype=float)
    k = np.asarray(kappas, dtype=float)[None]
    return float(_clearances(k, centre, object_radius, lengths_, base, geometry, theta, width)[0])


def sweep_speed(start: Floats, goal: Floats, lengths: Floats, geometry: GripperGeometry) -> float:
    """Bound on how fast any point of the arm or its fingers moves along the straight curvature
    interpolation from `start` to `goal` [1/m], per unit fraction of it [m].

    Bending segment i by d theta_i moves its own chord by at most L_i / 2 d theta_i (the chord
    is the integral over the arc of its direction) and turns everything distal to it about the
    segment's end, so a point moves by at most R_i d theta_i, R_i the arc length from the
    segment's start to the arm's tip plus the fingers' reach (root_offset + finger_length). The
    bend angles change linearly, by delta theta_i = L_i delta kappa_i: V = sum_i R_i |delta
    theta_i|."""
    lengths_ = np.asarray(lengths, dtype=float)
    delta = np.asarray(goal, dtype=float) - np.asarray(start, dtype=float)
    reach = geometry.root_offset + geometry.finger_length
    beyond = np.cumsum(lengths_[::-1])[::-1]  # arc length from each segment's start to the tip
    return float(np.sum((beyond + reach) * np.abs(delta) * lengths_))


def sweep_clearance(
    start: Floats,
    goal: Floats,
    centre: tuple[float, float],
    object_radius: float,
    lengths: Floats,
    base: Pose,
    geometry: GripperGeometry,
    theta: float,
    *,
    width: float = ARM_WIDTH,
) -> float:
    """Lower bound of the clearance [m] (as `clearance`) over the straight curvature
    interpolation from `start` to `goal` [1/m], both ends included.

    No point moves faster than V = `sweep_speed` per unit fraction, and the clearance is
    1-Lipschitz in every point's position; so sampling the fraction at n >= V / SWEEP_TOLERANCE
    steps and taking V / (2 n) off the smallest sampled clearance bounds it everywhere between
    the samples."""
    lengths_ = np.asarray(lengths, dtype=float)
    a, b = np.asarray(start, dtype=float), np.asarray(goal, dtype=float)
    speed = sweep_speed(a, b, lengths_, geometry)
    count = max(1, math.ceil(speed / SWEEP_TOLERANCE))
    fractions = np.linspace(0.0, 1.0, count + 1)
    chain = a + fractions[:, None] * (b - a)
    values = _clearances(chain, centre, object_radius, lengths_, base, geometry, theta, width)
    return float(np.min(values)) - 0.5 * speed / count
