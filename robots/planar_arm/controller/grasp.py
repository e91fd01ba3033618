"""Grasp-and-place planning of the planar arm with its soft gripper (issue 12; PHYSICS.md sec. 3).

The thesis's planar grasping manipulator approaches a randomly placed object along "concentric
approach circles" that shrink onto it, the gripper facing the object's centre, without touching
it; it then grasps the object, carries it to a place location and releases it. This module is
the controller's side of that: pure planning on the arm's curvatures, no plant state.

- `draw_grasp_task` draws an object and a place location that the arm can grasp at (both
  plannable from the arm's start), from the scenario's `numpy.random.Generator`.
- `plan_approach`: arm configurations whose tip poses lie on circles of standoff rho_k around the
  object centre (the tip at `tip_for_grasp(centre, heading, standoff=rho_k)`), rho_k shrinking to
  0 (the grasp pose). The approach heading is chosen among those at which every circle is
  reachable (heading-constrained IK) and every move is clear, by the shortest motion; the
  gripper then goes radially inwards at that one heading. (Entering the outer circle at another
  heading and going round it was tried and dropped: of 80 random starts with the object 3 to
  10 mm beside the arm's body, it rescued none of the 14 that found no clear approach; where
  the move onto the outer circle sweeps through the object at every heading, so does any other
  first move.)
- `plan_carry`: the grasp point (where the held object's centre sits) moved along a straight line
  to the place location, the heading changing linearly if it must (the place heading is the
  reachable one nearest the grasp heading, from which, given the object's radius, the gripper
  can also back off).
- `plan_retreat`: after release, the open gripper backed off along its axis to the outer radius.

"Without touching": every waypoint and every point of the straight curvature interpolation
between consecutive waypoints (what `robots.planar_arm.controller.tasks.CurvatureMove` tracks)
keeps the open
fingers' capsules (radius finger_width / 2) and the arm's backbone capsules (radius width / 2)
at least `margin` from the object's disk. The check is a guaranteed bound, not a sampled hope:
arcs are sampled as polylines less their sagitta, and along an interpolation the samples are
spaced so that no body point moves more than SWEEP_TOLERANCE between them (a Lipschitz bound on
the kinematics), and SWEEP_TOLERANCE / 2 is taken off. Where an interpolation is not clear, the
move is split at the middle pose (on the same radial line), solved by IK warm-started from its
neighbour, up to MAX_SPLITS times.

Invariant: every returned configuration lies within [lower, upper] and meets its tip pose by the
IK's tolerance; consecutive configurations come from warm-started IK; `GraspPlan.clearance` is a
lower bound of the clearance along the whole plan (start included) and is >= margin for the
approach and the retreat; every function is deterministic (the draw takes all its randomness
from the Generator passed in).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from controllers import kinematics
from robots.planar_arm.controller.gripper import (
    GripperGeometry,
    finger_points,
    grasp_point,
    tip_for_grasp,
)
from robots.planar_arm.controller.ik import solve_ik

Floats = Sequence[float] | np.ndarray
Pose = tuple[float, float, float]

ARM_WIDTH = 0.02  # [m] the planar arm's "rectangular" segments: backbone capsule radius 0.01 m
MARGIN = 1.5e-3  # [m] clearance kept between the object and the gripper or arm
CIRCLES = 4  # approach circles, the grasp pose (radius 0) included
HEADING_STEP = math.radians(10.0)  # [rad] grid of approach headings, and the step along a circle
CARRY_STEP = 0.02  # [m] grasp point travel between carry waypoints
BODY_SAMPLES = 16  # polyline points per segment and per finger (their sagitta is subtracted)
SWEEP_TOLERANCE = 5e-4  # [m] largest move of any body point between two checked configurations
MAX_SPLITS = 4  # halvings of one move before the interpolation check gives up on it
SEARCH_ITERATIONS = 25  # IK iterations of a warm-started solve (they meet the pose in < 15)
DRAW_ATTEMPTS = 200
DRAW_SHARE = 0.7  # share of each curvature range that drawn grasp poses need (see draw_targets)
START_MARGIN = 0.01  # [m] a drawn object's clearance from the arm in its start configuration
SEPARATION = 0.06  # [m] least distance between a drawn object and its place location
# [m] a drawn task is kept only if its plans keep this much more than `margin`: the controller
# plans again from estimates (the object's centre and the arm's start a fraction of a millimetre
# off, the grasp configuration settled a little off its plan), and a draw on the edge of
# plannable would fail there
DRAW_SLACK = 2e-3
# [1/m] and the approach must also be plannable (with `margin`) from the start configuration
# shaken by this much per segment, both ways (alternating signs): the controller plans from its
# estimate of the start, a tenth of a 1/m or so off, and some layouts are plannable from the
# exact start only
START_SHAKE = 0.15


@dataclass(frozen=True, eq=False)
class GraspPlan:
    """A sequence of arm configurations for one phase of grasp-and-place.

    Attributes
    ----------
    start
        The configuration the plan starts from, shape (N,) [1/m] (not a waypoint; the move from
        it to the first waypoint is part of the plan and checked like the others).
    waypoints
        (curvatures, shape (N,) [1/m]; tip pose (x [m], y [m], heading [rad])) in order. The pose
        is the one asked of the IK, its heading on the branch of the configuration's own tip
        heading (so headings along a plan are continuous).
    heading
        The gripper's heading at the last waypoint, wrapped to [-pi, pi] [rad]: the approach
        (grasp) heading, the place heading, or the retreat's axis.
    radii
        The circles' standoffs [m], outer first (approach: ending with 0; retreat: ending with
        the outer radius; carry: empty).
    centre
        The circles' centre: the object's (approach), the place location (carry, retreat) [m].
    standoffs
        Each waypoint's standoff from `centre` along the gripper axis [m] (0 throughout a carry).
    clearance
        Lower bound of the object's clearance from the open fingers and the backbone over the
        whole plan, interpolations included [m]; inf for a carry (the object is in the hand).
    """

    start: np.ndarray
    waypoints: tuple[tuple[np.ndarray, Pose], ...]
    heading: float
    radii: tuple[float, ...]
    centre: tuple[float, float]
    standoffs: tuple[float, ...]
    clearance: float

    @property
    def kappas(self) -> np.ndarray:
        """The waypoints' curvatures, shape (n, N) [1/m]."""
        return np.array([k for k, _ in self.waypoints])

    @property
    def poses(self) -> np.ndarray:
        """The waypoints' tip poses, shape (n, 3)."""
        return np.array([p for _, p in self.waypoints])

    def motion(self) -> float:
        """Sum over the moves (start included) of the largest curvature change [1/m]: what the
        synchronised curvature moves' durations scale with."""
        chain = np.vstack((self.start, self.kappas))
        return float(np.sum(np.max(np.abs(np.diff(chain, axis=0)), axis=1)))


# ---------------------------------------------------------------------- clearance


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


# ---------------------------------------------------------------------- planning


@dataclass(frozen=True)
class _Arm:
    """The arm, its limits and the gripper: what every planning step needs."""

    lengths: np.ndarray
    base: Pose
    lower: np.ndarray
    upper: np.ndarray
    geometry: GripperGeometry
    width: float

    @classmethod
    def of(
        cls,
        lengths: Floats,
        base: Pose,
        lower: Floats,
        upper: Floats,
        geometry: GripperGeometry,
        width: float,
    ) -> _Arm:
        lengths_ = np.asarray(lengths, dtype=float)
        lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
        if lo.shape != lengths_.shape or hi.shape != lengths_.shape:
            raise ValueError(
                f"grasp planning: bounds of {lo.size} and {hi.size} segments "
                f"for {lengths_.size} segment lengths"
            )
        if width < 0.0:
            raise ValueError(f"grasp planning: arm width {width} m must not be negative")
        pose = (float(base[0]), float(base[1]), float(base[2]))
        return cls(lengths_, pose, lo, hi, geometry, width)

    def tip(self, kappas: np.ndarray) -> np.ndarray:
        return kinematics.forward(kappas, self.lengths, self.base)[-1]

    def solve(
        self, pose: Pose, initial: np.ndarray, max_iter: int = SEARCH_ITERATIONS
    ) -> np.ndarray | None:
        """Curvatures meeting the tip pose, warm-started from `initial`; None if the IK fails."""
        result = solve_ik(
            pose[:2],
            initial,
            self.lengths,
            self.base,
            self.lower,
            self.upper,
            heading=pose[2],
            max_iter=max_iter,
        )
        return result.kappas if result.converged else None

    def seed(self, point: Floats, standoff: float, initial: np.ndarray) -> np.ndarray | None:
        """Some configuration that holds `point` at the grasp point backed off by `standoff`,
        with whatever heading: position-only IK of the arm extended by a straight virtual
        segment (bounds [0, 0]) of length grasp_offset + standoff."""
        reach = self.geometry.grasp_offset + standoff
        result = solve_ik(
            np.asarray(point, dtype=float),
            np.append(initial, 0.0),
            np.append(self.lengths, reach),
            self.base,
            np.append(self.lower, 0.0),
            np.append(self.upper, 0.0),
        )
        return result.kappas[:-1] if result.converged else None


@dataclass(frozen=True)
class _Node:
    """A waypoint under construction: configuration, and the pose it was solved for."""

    kappas: np.ndarray
    standoff: float
    heading: float  # [rad] unwrapped along the plan


@dataclass(frozen=True)
class _Obstacle:
    """The object the open gripper must not touch, and the required clearance."""

    centre: tuple[float, float]
    radius: float
    margin: float


def _waypoint(arm: _Arm, centre: Floats, node: _Node) -> tuple[np.ndarray, Pose]:
    x, y, h = tip_for_grasp(
        arm.geometry, (float(centre[0]), float(centre[1])), node.heading, node.standoff
    )
    actual = float(arm.tip(node.kappas)[2])
    return node.kappas, (x, y, actual + math.remainder(h - actual, 2.0 * math.pi))


def _sweep(arm: _Arm, obstacle: _Obstacle, a: np.ndarray, b: np.ndarray) -> float:
    return sweep_clearance(
        a,
        b,
        obstacle.centre,
        obstacle.radius,
        arm.lengths,
        arm.base,
        arm.geometry,
        arm.geometry.theta_open,
        width=arm.width,
    )


def _connect(
    arm: _Arm, obstacle: _Obstacle, a: _Node, b: _Node, splits: int = MAX_SPLITS
) -> tuple[list[_Node], float] | None:
    """Nodes after `a` up to `b` whose moves all keep the margin, with their least clearance:
    the move a-b itself if it is clear, else split at the middle pose (mean standoff and
    heading: on the same radial line or circle), solved warm-started from `a`; None if no
    split within `splits` halvings is clear."""
    value = _sweep(arm, obstacle, a.kappas, b.kappas)
    if value >= obstacle.margin:
        return [b], value
    if splits == 0:
        return None
    standoff, heading = 0.5 * (a.standoff + b.standoff), 0.5 * (a.heading + b.heading)
    kappas = arm.solve(tip_for_grasp(arm.geometry, obstacle.centre, heading, standoff), a.kappas)
    if kappas is None:
        return None
    middle = _Node(kappas, standoff, heading)
    first = _connect(arm, obstacle, a, middle, splits - 1)
    if first is None:
        return None
    second = _connect(arm, obstacle, middle, b, splits - 1)
    if second is None:
        return None
    return first[0] + second[0], min(first[1], second[1])


def _chain(
    arm: _Arm, obstacle: _Obstacle, start: np.ndarray, nodes: Sequence[_Node]
) -> tuple[list[_Node], float] | None:
    """The nodes with every move (from `start` to the first node too) clear of the object,
    split where needed; None if some move cannot be made clear. The move from the start is not
    split (its middle pose is on no circle): it must be clear as it is."""
    value = _sweep(arm, obstacle, start, nodes[0].kappas)
    if value < obstacle.margin:
        return None
    out = [nodes[0]]
    for a, b in zip(nodes[:-1], nodes[1:], strict=True):
        joined = _connect(arm, obstacle, a, b)
        if joined is None:
            return None
        out.extend(joined[0])
        value = min(value, joined[1])
    return out, value


def _ring(
    arm: _Arm, centre: Floats, standoff: float, heading: float, kappas: np.ndarray
) -> Iterator[tuple[int, float, np.ndarray]]:
    """The reachable poses (index j, heading, curvatures) on the circle of `standoff` around
    `centre` at headings heading + j HEADING_STEP, nearest first (j = 0, 1, -1, 2, -2, ...):
    continuation from the known solution `kappas` at `heading` in both directions, each solve
    warm-started from its neighbour, a direction ending at its first failure or half a turn."""
    yield 0, heading, kappas
    current: dict[int, np.ndarray | None] = {1: kappas, -1: kappas}
    for j in range(1, int(math.pi / HEADING_STEP) + 1):
        for direction in (1, -1):
            previous = current[direction]
            if previous is None:
                continue
            h = heading + direction * j * HEADING_STEP
            pose = tip_for_grasp(arm.geometry, (float(centre[0]), float(centre[1])), h, standoff)
            solved = arm.solve(pose, previous)
            current[direction] = solved
            if solved is not None:
                yield direction * j, h, solved


def _motion(chain: Sequence[np.ndarray]) -> float:
    return float(sum(np.max(np.abs(b - a)) for a, b in zip(chain[:-1], chain[1:], strict=True)))


def default_radii(object_radius: float, geometry: GripperGeometry) -> tuple[float, ...]:
    """CIRCLES standoffs [m], outer first, evenly spaced down to 0: the outer one puts the open
    fingertips clear of the object (the finger length plus the object's diameter)."""
    outer = geometry.finger_length + 2.0 * object_radius
    return tuple(outer * (CIRCLES - 1 - k) / (CIRCLES - 1) for k in range(CIRCLES))


def _check_object(arm: _Arm, obstacle: _Obstacle, current: np.ndarray, what: str) -> None:
    if not obstacle.radius > 0.0:
        raise ValueError(f"grasp planning: object radius {obstacle.radius} m must be positive")
    if not obstacle.margin > 0.0:
        raise ValueError(f"grasp planning: margin {obstacle.margin} m must be positive")
    # the gripper alone at the grasp pose: the object must pass between the open fingers and
    # stay clear of the arm's end (its capsule reaches width / 2 ahead of the tip)
    gripper = arm.geometry
    tip = tip_for_grasp(gripper, (0.0, 0.0), 0.0)
    fingers = min(
        float(np.min(np.linalg.norm(points, axis=1))) - 0.5 * gripper.finger_width
        for points in finger_points(gripper, tip, gripper.theta_open, BODY_SAMPLES)
    )
    if min(fingers, gripper.grasp_offset - 0.5 * arm.width) - obstacle.radius < obstacle.margin:
        raise ValueError(
            f"grasp planning: an object of radius {obstacle.radius} m does not fit the open "
            f"gripper (between the fingers, ahead of the arm's end) with a margin of "
            f"{obstacle.margin} m"
        )
    now = _sweep(arm, obstacle, current, current)
    if now < obstacle.margin:
        raise ValueError(
            f"grasp planning: {what} at ({obstacle.centre[0]:.4f}, {obstacle.centre[1]:.4f}) m "
            f"is {now * 1e3:.2f} mm from the arm in its current configuration "
            f"(open fingers), less than the margin {obstacle.margin * 1e3:.2f} mm"
        )


def _check_radii(radii: Floats, last: str) -> tuple[float, ...]:
    """The radii as floats, checked: shrinking strictly to 0 (`last` "zero", an approach) or
    growing strictly from 0 (`last` "outer", a retreat)."""
    values = tuple(float(r) for r in radii)
    if len(values) < 2 or any(not math.isfinite(r) or r < 0.0 for r in values):
        raise ValueError(f"grasp planning: radii {values} must be at least two finite values >= 0")
    steps = np.diff(values)
    if last == "zero" and (values[-1] != 0.0 or np.any(steps >= 0.0)):
        raise ValueError(f"grasp planning: approach radii {values} must shrink strictly to 0")
    if last == "outer" and (values[0] != 0.0 or np.any(steps <= 0.0)):
        raise ValueError(f"grasp planning: retreat radii {values} must grow strictly from 0")
    return values


def plan_approach(
    centre: tuple[float, float],
    object_radius: float,
    current_kappas: Floats,
    lengths: Floats,
    base: Pose,
    lower: Floats,
    upper: Floats,
    geometry: GripperGeometry,
    *,
    radii: Floats | None = None,
    margin: float = MARGIN,
    width: float = ARM_WIDTH,
    accept: Callable[[GraspPlan], bool] | None = None,
) -> GraspPlan:
    """Waypoints that bring the open gripper onto concentric circles shrinking onto the object
    and finally to the grasp pose, never touching the object.

    Parameters
    ----------
    centre, object_radius
        The object's disk [m].
    current_kappas
        The arm's configuration now, shape (N,) [1/m]; the plan's first move starts here.
    lengths, base, lower, upper
        Segment lengths [m], base pose, curvature bounds [1/m] (as `solve_ik`).
    geometry
        The gripper; its fingers are open (`theta_open`) throughout.
    radii
        Standoffs of the circles [m], strictly shrinking to 0; default `default_radii`.
    margin
        Clearance kept between the object's disk and the fingers and backbone [m], > 0.
    width
        The arm's backbone width [m] (capsules of radius width / 2).
    accept
        What the task needs of an approach beyond clearance (for example that the object can
        be carried on from its grasp configuration): a clear plan it rejects is passed over for
        the next best heading.

    Returns
    -------
    GraspPlan
        Waypoints on the circles, outer first, ending at the grasp pose (standoff 0), at the
        heading of least motion (the sum of the largest curvature change of each move) among
        those that can be made clear (and that `accept` accepts).

    Raises
    ------
    ValueError
        When the object is out of reach, touches the arm now, does not fit the open gripper,
        or no approach heading gives clear moves (that `accept` accepts).
    """
    arm = _Arm.of(lengths, base, lower, upper, geometry, width)
    current = np.clip(np.asarray(current_kappas, dtype=float), arm.lower, arm.upper)
    obstacle = _Obstacle((float(centre[0]), float(centre[1])), float(object_radius), margin)
    circles = _check_radii(
        default_radii(object_radius, geometry) if radii is None else radii, "zero"
    )
    _check_object(arm, obstacle, current, "the object")
    where = f"object at ({centre[0]:.4f}, {centre[1]:.4f}) m"
    reach = float(np.sum(arm.lengths)) + geometry.grasp_offset
    if math.hypot(centre[0] - arm.base[0], centre[1] - arm.base[1]) > reach:
        raise ValueError(f"grasp planning: {where} is beyond the arm's reach {reach:.3f} m")
    seed = arm.seed(centre, 0.0, current)
    if seed is None:
        seed = arm.seed(centre, 0.0, 0.5 * (arm.lower + arm.upper))
    if seed is None:
        raise ValueError(f"grasp planning: no grasp pose reaches the {where}")
    grasps = list(_ring(arm, centre, 0.0, float(arm.tip(seed)[2]), seed))
    # best first with a bound: a heading's motion is at least the largest curvature change from
    # now to its grasp configuration (triangle inequality), so its circles need solving only
    # while that bound is below the best motion found; the best is then checked for clearance
    grasps.sort(key=lambda g: float(np.max(np.abs(g[2] - current))))
    candidates: list[tuple[float, list[_Node]]] = []
    reachable = rejected = 0
    while True:
        best = min(candidates, key=lambda c: c[0], default=None)
        if grasps and (best is None or float(np.max(np.abs(grasps[0][2] - current))) < best[0]):
            _, heading, kappas = grasps.pop(0)
            nodes = _inwards(arm, obstacle.centre, circles, heading, kappas)
            if nodes is not None:
                reachable += 1
                candidates.append((_motion([current] + [n.kappas for n in nodes]), nodes))
            continue
        if best is None:
            break
        candidates.remove(best)
        chained = _chain(arm, obstacle, current, best[1])
        if chained is not None:
            plan = _plan(arm, obstacle, current, circles, *chained)
            if accept is None or accept(plan):
                return plan
            rejected += 1
    raise ValueError(
        f"grasp planning: no approach heading keeps the arm {margin * 1e3:.2f} mm clear of the "
        f"{where} ({reachable} headings with every circle reachable"
        + (f", {rejected} clear but not accepted" if rejected else "")
        + ")"
    )


def _inwards(
    arm: _Arm,
    centre: tuple[float, float],
    circles: tuple[float, ...],
    heading: float,
    kappas: np.ndarray,
) -> list[_Node] | None:
    """The nodes on every circle at `heading`, outer first, solved outwards from the grasp
    configuration `kappas` (each warm-started from the next inner one); None if one fails."""
    nodes = [_Node(kappas, 0.0, heading)]
    for standoff in circles[-2::-1]:
        pose = tip_for_grasp(arm.geometry, centre, heading, standoff)
        solved = arm.solve(pose, nodes[-1].kappas)
        if solved is None:
            return None
        nodes.append(_Node(solved, standoff, heading))
    return nodes[::-1]


def _plan(
    arm: _Arm,
    obstacle: _Obstacle,
    start: np.ndarray,
    radii: tuple[float, ...],
    nodes: Sequence[_Node],
    value: float,
) -> GraspPlan:
    waypoints = tuple(_waypoint(arm, obstacle.centre, n) for n in nodes)
    return GraspPlan(
        start=start,
        waypoints=waypoints,
        heading=math.remainder(waypoints[-1][1][2], 2.0 * math.pi),
        radii=radii,
        centre=obstacle.centre,
        standoffs=tuple(n.standoff for n in nodes),
        clearance=value,
    )


def plan_retreat(
    place: Floats,
    object_radius: float,
    current_kappas: Floats,
    heading: float,
    lengths: Floats,
    base: Pose,
    lower: Floats,
    upper: Floats,
    geometry: GripperGeometry,
    *,
    radii: Floats | None = None,
    margin: float = MARGIN,
    width: float = ARM_WIDTH,
) -> GraspPlan:
    """After release at `place`: the open gripper backed off along its axis (`heading` [rad])
    through the circles' standoffs out to the outer one, never touching the object.

    Parameters are as `plan_approach`; `radii` are the standoffs outwards, strictly growing from
    0 (default: `default_radii` reversed). The plan starts at `current_kappas` (the release
    configuration, standoff 0), whose open fingers must already clear the object.

    Raises
    ------
    ValueError
        When the open fingers at the release configuration touch the object, or a standoff is
        unreachable or cannot be reached without touching it.
    """
    arm = _Arm.of(lengths, base, lower, upper, geometry, width)
    current = np.clip(np.asarray(current_kappas, dtype=float), arm.lower, arm.upper)
    obstacle = _Obstacle((float(place[0]), float(place[1])), float(object_radius), margin)
    default = default_radii(object_radius, geometry)[::-1]
    circles = _check_radii(default if radii is None else radii, "outer")
    _check_object(arm, obstacle, current, "the released object")
    nodes = []
    previous = current
    for standoff in circles[1:]:
        solved = arm.solve(tip_for_grasp(geometry, obstacle.centre, heading, standoff), previous)
        if solved is None:
            raise ValueError(
                f"grasp planning: backing off {standoff * 1e3:.1f} mm from the place "
                f"({place[0]:.4f}, {place[1]:.4f}) m at heading {heading:.3f} rad is unreachable"
            )
        nodes.append(_Node(solved, standoff, heading))
        previous = solved
    start = _Node(current, 0.0, heading)
    chained = _chain(arm, obstacle, current, [start, *nodes])
    if chained is None:
        raise ValueError(
            f"grasp planning: backing off from the place ({place[0]:.4f}, {place[1]:.4f}) m "
            f"does not keep {margin * 1e3:.2f} mm clear of the released object"
        )
    return _plan(arm, obstacle, current, circles, chained[0][1:], chained[1])


def plan_carry(
    place: Floats,
    current_kappas: Floats,
    heading: float,
    lengths: Floats,
    base: Pose,
    lower: Floats,
    upper: Floats,
    geometry: GripperGeometry,
    *,
    step: float = CARRY_STEP,
    heading_step: float = HEADING_STEP,
    object_radius: float | None = None,
    radii: Floats | None = None,
    margin: float = MARGIN,
    width: float = ARM_WIDTH,
) -> GraspPlan:
    """Waypoints that carry the held object from the grasp configuration to `place`.

    The grasp point moves along the straight line from where it is now (the grasp point of
    `current_kappas`' tip) to `place`, at most `step` [m] per waypoint, the heading changing
    linearly from `heading` [rad] to the place heading, at most `heading_step` [rad] per
    waypoint; each waypoint is solved warm-started from the previous one. The place heading is
    the one nearest `heading` (on a HEADING_STEP grid) for which the whole line is reachable
    and, when `object_radius` is given, the retreat (`plan_retreat` with `radii`, `margin`,
    `width`) after release is possible too.

    Raises
    ------
    ValueError
        When no place heading gives a reachable carry (and retreat).
    """
    arm = _Arm.of(lengths, base, lower, upper, geometry, width)
    if not step > 0.0 or not heading_step > 0.0:
        raise ValueError(f"grasp planning: carry steps {step} m, {heading_step} rad must be > 0")
    current = np.clip(np.asarray(current_kappas, dtype=float), arm.lower, arm.upper)
    origin = grasp_point(geometry, tuple(arm.tip(current)))  # type: ignore[arg-type]
    target = np.array(place, dtype=float)
    where = f"place ({place[0]:.4f}, {place[1]:.4f}) m"
    reach = float(np.sum(arm.lengths)) + geometry.grasp_offset
    if math.hypot(target[0] - arm.base[0], target[1] - arm.base[1]) > reach:
        raise ValueError(f"grasp planning: the {where} is beyond the arm's reach {reach:.3f} m")
    # the place's reachable headings: continuation round it from the carry heading if that is
    # reachable there, else from whatever heading a position-only solve finds
    seed = arm.solve(tip_for_grasp(geometry, tuple(target), heading), current)
    start_heading = heading
    if seed is None:
        seed = arm.seed(target, 0.0, current)
        if seed is None:
            raise ValueError(f"grasp planning: no grasp pose reaches the {where}")
        tip_heading = float(arm.tip(seed)[2])
        start_heading = heading + math.remainder(tip_heading - heading, 2.0 * math.pi)
    # nearest first: the ring yields them in that order when it starts at `heading`
    finals: Iterable[float] = (h for _, h, _ in _ring(arm, target, 0.0, start_heading, seed))
    if start_heading != heading:
        finals = sorted(finals, key=lambda h: abs(h - heading))
    distance = float(np.linalg.norm(target - origin))
    for final in finals:
        turn = final - heading
        count = max(1, math.ceil(distance / step), math.ceil(abs(turn) / heading_step))
        waypoints = []
        previous = current
        for i in range(1, count + 1):
            s = i / count
            point = origin + s * (target - origin)
            h = heading + s * turn
            pose = tip_for_grasp(geometry, (float(point[0]), float(point[1])), h)
            solved = arm.solve(pose, previous)
            if solved is None:
                break
            actual = float(arm.tip(solved)[2])
            waypoints.append(
                (solved, (pose[0], pose[1], actual + math.remainder(h - actual, 2 * math.pi)))
            )
            previous = solved
        else:
            if object_radius is not None:
                try:
                    plan_retreat(
                        place,
                        object_radius,
                        previous,
                        final,
                        lengths,
                        base,
                        lower,
                        upper,
                        geometry,
                        radii=radii,
                        margin=margin,
                        width=width,
                    )
                except ValueError:
                    continue
            return GraspPlan(
                start=current,
                waypoints=tuple(waypoints),
                heading=math.remainder(final, 2.0 * math.pi),
                radii=(),
                centre=(float(place[0]), float(place[1])),
                standoffs=(0.0,) * len(waypoints),
                clearance=math.inf,
            )
    raise ValueError(
        f"grasp planning: no place heading carries the object from ({origin[0]:.4f}, "
        f"{origin[1]:.4f}) m to the {where}"
        + ("" if object_radius is None else " and backs off clear of it")
    )


# ---------------------------------------------------------------------- tasks


def draw_grasp_task(
    rng: np.random.Generator,
    lengths: Floats,
    base: Pose,
    lower: Floats,
    upper: Floats,
    geometry: GripperGeometry,
    object_radius: float,
    start_kappas: Floats,
    *,
    share: float = DRAW_SHARE,
    start_margin: float = START_MARGIN,
    separation: float = SEPARATION,
    margin: float = MARGIN,
    width: float = ARM_WIDTH,
    plannable: bool = True,
    slack: float = DRAW_SLACK,
    shake: float = START_SHAKE,
    attempts: int = DRAW_ATTEMPTS,
) -> tuple[tuple[float, float], tuple[float, float]]:
    """An object position and a place position [m] for a grasp-and-place task.

    Each is the grasp point of a tip pose drawn as `draw_targets` draws targets (curvatures
    uniform within the middle `share` of each segment's range), and must be a grasp pose that
    the heading-constrained IK reaches from `start_kappas` within those shrunk bounds. The object
    keeps `start_margin` [m] from the arm in its start configuration (backbone and open
    fingers); the place is at least `separation` [m] from the object and does not overlap the
    object's start (two radii plus `margin` apart). With `plannable`, the draw is also kept
    only if `plan_approach` from the start and `plan_carry` (with the retreat) succeed with
    `margin + slack`, and `plan_approach` with `margin` from the start shaken by `shake` [1/m]
    both ways, so the controller, planning with `margin` from its estimates, can do the task.
    Deterministic: all randomness comes from `rng`.

    Raises
    ------
    ValueError
        When no draw within `attempts` meets these conditions.
    """
    arm = _Arm.of(lengths, base, lower, upper, geometry, width)
    if not 0.0 < share <= 1.0:
        raise ValueError(f"grasp task: share {share} must be in (0, 1]")
    start = np.asarray(start_kappas, dtype=float)
    mid, half = 0.5 * (arm.lower + arm.upper), 0.5 * (arm.upper - arm.lower) * share
    shrunk = _Arm(arm.lengths, arm.base, mid - half, mid + half, geometry, width)

    def draw() -> tuple[np.ndarray, float] | None:
        kappas = rng.uniform(shrunk.lower, shrunk.upper)
        tip = arm.tip(kappas)
        point = grasp_point(geometry, (float(tip[0]), float(tip[1]), float(tip[2])))
        pose = tip_for_grasp(geometry, (float(point[0]), float(point[1])), float(tip[2]))
        if shrunk.solve(pose, start, max_iter=100) is None:
            return None
        return point, float(tip[2])

    for _ in range(attempts):
        drawn = draw()
        if drawn is None:
            continue
        centre = (float(drawn[0][0]), float(drawn[0][1]))
        other = draw()
        if other is None:
            continue
        place = (float(other[0][0]), float(other[0][1]))
        apart = math.dist(centre, place)
        if apart < max(separation, 2.0 * object_radius + margin):
            continue
        near = clearance(
            start,
            centre,
            object_radius,
            arm.lengths,
            arm.base,
            geometry,
            geometry.theta_open,
            width=width,
        )
        if near < start_margin:
            continue
        if plannable:
            try:
                approach = plan_approach(
                    centre,
                    object_radius,
                    start,
                    lengths,
                    base,
                    lower,
                    upper,
                    geometry,
                    margin=margin + slack,
                    width=width,
                )
                plan_carry(
                    place,
                    approach.waypoints[-1][0],
                    approach.waypoints[-1][1][2],
                    lengths,
                    base,
                    lower,
                    upper,
                    geometry,
                    object_radius=object_radius,
                    margin=margin + slack,
                    width=width,
                )
                pattern = np.where(np.arange(start.size) % 2 == 0, shake, -shake)
                for shaken in (start + pattern, start - pattern):
                    plan_approach(
                        centre,
                        object_radius,
                        shaken,
                        lengths,
                        base,
                        lower,
                        upper,
                        geometry,
                        margin=margin,
                        width=width,
                    )
            except ValueError:
                continue
        return centre, place
    raise ValueError(f"grasp task: no object and place found in {attempts} draws")
