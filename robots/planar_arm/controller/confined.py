"""Whole-arm planning of the planar arm in confined spaces (issue 12; PHYSICS.md sections 3, 6).

The thesis advances its six-segment "cylindrical actuator" arm through pipe-like sections by "a
sequence of constrained nonlinear optimisations over the arm's configuration that keep its
envelope inside the environment while advancing the tip, tolerating collisions rather than
preventing them". `plan_whole_arm` is that sequence: each step is one SLSQP problem over the
curvatures whose objective pulls the tip towards a point a little ahead along the channel's
centreline (so it follows the pipe instead of cutting corners) with a smoothness term on the
change, under the constraints that every sampled backbone point keeps `width / 2 + margin` from
the walls and that no curvature changes by more than a trust region. Where the clearance
constraints cannot be met, or can be met only by not advancing (a pipe narrower than the arm
plus its margins), the step is solved again with a penalised slack on the clearance (the
collision is tolerated and reported in `Plan.slack_steps`) instead of failing or stalling.
The waypoints are then tracked by the curvature controllers as synchronised curvature moves
(robots.planar_arm.controller.tasks.CurvatureMove), which interpolate the curvatures linearly; so
each step is
also checked along that interpolation and its trust region halved until the body stays clear
of the walls between waypoints too.

Why SLSQP: the problem is small (six curvatures, about fifty smooth inequality constraints with
analytic Jacobians, box bounds) and warm-started from the previous waypoint, where SQP's
superlinear convergence takes a handful of iterations. trust-constr (interior point) plans the
same waypoints but measured 5 to 8 times slower (pipe 1: 2.8 s against 0.35 s; pipe 4: 3.2 s
against 0.67 s), for no gain at this size.

Invariant: every returned configuration lies within [lower, upper], consecutive configurations
differ by at most `step` per segment, and the plan is a deterministic function of its inputs (no
randomness; SLSQP is deterministic).

The channel's walls are what the Environment FMU takes (at most 2 polylines of 16 vertices) and
the sampled backbone points are the FMU's (s = L k / n, k = 1..n per segment; the base is
clamped), so a plan with `clearance_min >= width / 2` is one the FMU sees without penetration.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize

from controllers import kinematics

Point = tuple[float, float]
Floats = Sequence[float] | np.ndarray

MAX_WALLS = 2  # the Environment FMU's capacity
MAX_VERTICES = 16

# the "cylindrical actuator" arm of the thesis's confined-space experiments [estimate]
SEGMENTS = 6
SEGMENT_LENGTH = 0.06  # [m]
WIDTH = 0.016  # [m] diameter of the cylindrical actuator
KAPPA_LIMIT = 20.0  # [1/m] planning bound of each curvature (radius 5 cm)

SMALL_HALF_ANGLE = 1e-2  # [rad] below it sinc and its derivative take their series
FEASIBLE = 1e-7  # [m] constraint violation that still counts as met (SLSQP's rounding)
INTERPOLATION_CHECKS = (0.25, 0.5, 0.75)  # fractions of a step checked between waypoints
MAX_HALVINGS = 4  # trust-region halvings of one step before the interpolation check gives up
STALL_STEPS = 12  # steps without progress that end a plan as stalled
STALL_PROGRESS = 2e-4  # [m] progress that counts over STALL_STEPS


@dataclass(frozen=True)
class Channel:
    """A planar channel: up to two wall polylines and a centreline along it.

    The allowed region is the polygon bounded by the walls: wall 1 followed by wall 2 reversed
    (one wall: itself), closed by straight openings between their ends that are not walls (the
    mouth behind the arm's base and the far end of the pipe). Inside it the clearance of a point
    is its distance to the nearest wall edge; outside, minus that distance. The sign is decided by
    the even-odd rule on that polygon, which needs no orientation convention and is exact for the
    simple polygon checked at construction; the clearance is continuous across walls (zero on
    them) and jumps only across the openings, which the pipes put out of the arm's reach.

    Parameters
    ----------
    walls
        Wall polylines [(x, y), ...] [m]: at most MAX_WALLS, each of 2 to MAX_VERTICES vertices.
    centreline
        Polyline [(x, y), ...] [m] that the tip should follow, from the base to beyond the goal;
        progress along the channel is arc length along it.
    """

    walls: tuple[tuple[Point, ...], ...]
    centreline: tuple[Point, ...]
    _edges: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False, compare=False)
    _polygon: np.ndarray = field(init=False, repr=False, compare=False)
    _stations: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        walls = tuple(tuple((float(x), float(y)) for x, y in wall) for wall in self.walls)
        centreline = tuple((float(x), float(y)) for x, y in self.centreline)
        object.__setattr__(self, "walls", walls)
        object.__setattr__(self, "centreline", centreline)
        if not 1 <= len(walls) <= MAX_WALLS:
            raise ValueError(f"channel: {len(walls)} walls, the environment takes 1 to {MAX_WALLS}")
        for index, wall in enumerate(walls, start=1):
            if not 2 <= len(wall) <= MAX_VERTICES:
                raise ValueError(
                    f"channel: wall {index} has {len(wall)} vertices, not 2 to {MAX_VERTICES}"
                )
        if len(centreline) < 2:
            raise ValueError("channel: the centreline needs at least 2 points")
        if not all(math.isfinite(v) for line in (*walls, centreline) for p in line for v in p):
            raise ValueError("channel: a wall or centreline coordinate is not finite")
        starts = np.concatenate([np.array(wall[:-1]) for wall in walls])
        ends = np.concatenate([np.array(wall[1:]) for wall in walls])
        if np.any(np.linalg.norm(ends - starts, axis=1) == 0.0):
            raise ValueError("channel: a wall has two equal consecutive vertices")
        polygon = np.array(walls[0] + (tuple(reversed(walls[1])) if len(walls) == 2 else ()))
        _check_simple(polygon)
        line = np.array(centreline)
        pieces = np.linalg.norm(np.diff(line, axis=0), axis=1)
        if np.any(pieces == 0.0):
            raise ValueError("channel: the centreline has two equal consecutive points")
        object.__setattr__(self, "_edges", (starts, ends))
        object.__setattr__(self, "_polygon", polygon)
        object.__setattr__(self, "_stations", np.concatenate(([0.0], np.cumsum(pieces))))

    # ------------------------------------------------------------------ clearance

    def inside(self, points: np.ndarray) -> np.ndarray:
        """Whether each point (shape (n, 2) [m]) lies in the allowed region (even-odd rule)."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        a = self._polygon
        b = np.roll(a, -1, axis=0)
        # a horizontal ray to +x crosses edge a-b where the edge straddles the point's y
        straddles = (a[None, :, 1] > p[:, None, 1]) != (b[None, :, 1] > p[:, None, 1])
        dy = np.where(straddles, b[:, 1] - a[:, 1], 1.0)
        x_cross = a[:, 0] + (p[:, None, 1] - a[:, 1]) * (b[:, 0] - a[:, 0]) / dy
        crossings = np.count_nonzero(straddles & (x_cross > p[:, None, 0]), axis=1)
        return np.asarray(crossings % 2 == 1)

    def clearance_and_gradient(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed clearance of each point [m] (positive inside) and its gradient, shape (n, 2).

        The gradient is the unit vector from the nearest wall point to the point, times the
        sign; on a wall (distance zero) it is the nearest edge's normal pointing inside."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        a, b = self._edges
        ab = b - a
        t = np.clip(
            np.einsum("pek,ek->pe", p[:, None, :] - a[None], ab) / np.sum(ab * ab, axis=1),
            0.0,
            1.0,
        )
        nearest = a[None] + t[..., None] * ab[None]
        offset = p[:, None, :] - nearest
        distance2 = np.sum(offset * offset, axis=2)
        edge = np.argmin(distance2, axis=1)
        rows = np.arange(len(p))
        distance = np.sqrt(distance2[rows, edge])
        sign = np.where(self.inside(p), 1.0, -1.0)
        vector = offset[rows, edge]
        normal = np.stack((-ab[edge, 1], ab[edge, 0]), axis=1)
        on_wall = distance == 0.0
        with np.errstate(invalid="ignore", divide="ignore"):
            unit = np.where(on_wall[:, None], 0.0, vector / distance[:, None])
        if np.any(on_wall):
            # pointing into the region: the side where a small step along the normal is inside
            normal = normal / np.linalg.norm(normal, axis=1)[:, None]
            probe = self.inside(p[on_wall] + 1e-9 * normal[on_wall])
            unit[on_wall] = np.where(probe[:, None], normal[on_wall], -normal[on_wall])
            sign = np.where(on_wall, 1.0, sign)
        return sign * distance, sign[:, None] * unit

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Signed clearance [m] of each point (shape (n, 2)): the distance to the nearest wall
        edge, positive inside the allowed region and negative outside."""
        return self.clearance_and_gradient(points)[0]

    # ------------------------------------------------------------------ centreline

    @property
    def length(self) -> float:
        """Arc length of the centreline [m]."""
        return float(self._stations[-1])

    def progress(self, points: np.ndarray) -> np.ndarray:
        """Arc length [m] along the centreline of each point's nearest centreline point."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        line = np.array(self.centreline)
        a, ab = line[:-1], np.diff(line, axis=0)
        lengths = np.diff(self._stations)
        t = np.clip(
            np.einsum("pek,ek->pe", p[:, None, :] - a[None], ab) / (lengths * lengths), 0.0, 1.0
        )
        offset = p[:, None, :] - (a[None] + t[..., None] * ab[None])
        piece = np.argmin(np.sum(offset * offset, axis=2), axis=1)
        rows = np.arange(len(p))
        return np.asarray(self._stations[piece] + t[rows, piece] * lengths[piece])

    def point_at(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """Centreline point [m] and unit tangent at arc length `s` (clamped to the line)."""
        s = min(max(s, 0.0), self.length)
        piece = min(
            int(np.searchsorted(self._stations, s, side="right")) - 1, len(self._stations) - 2
        )
        line = np.array(self.centreline)
        tangent = (line[piece + 1] - line[piece]) / (
            self._stations[piece + 1] - self._stations[piece]
        )
        return line[piece] + (s - self._stations[piece]) * tangent, tangent


def _check_simple(polygon: np.ndarray) -> None:
    """Raise ValueError when two non-adjacent edges of the closed polygon cross."""
    n = len(polygon)
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue  # adjacent through the closing edge
            if _segments_cross(polygon[i], polygon[(i + 1) % n], polygon[j], polygon[(j + 1) % n]):
                raise ValueError(
                    f"channel: the walls cross (edges {i} and {j} of the region's outline)"
                )


def _segments_cross(p: np.ndarray, q: np.ndarray, r: np.ndarray, s: np.ndarray) -> bool:
    def orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
        return float((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))

    d1, d2, d3, d4 = orient(r, s, p), orient(r, s, q), orient(p, q, r), orient(p, q, s)
    return d1 * d2 < 0.0 and d3 * d4 < 0.0


# ---------------------------------------------------------------------- backbone


def sample_backbone(
    kappas: Floats, lengths: Floats, base: tuple[float, float, float], per_segment: int
) -> tuple[np.ndarray, np.ndarray]:
    """The Environment FMU's backbone points and their Jacobian on the curvatures.

    Points at s = L_j k / n (k = 1..n) on every segment j, the base excluded (it is clamped).

    Returns
    -------
    points, jacobian
        Positions, shape (N n, 2) [m], and d position / d kappa, shape (N n, 2, N) [m per 1/m]:
        as kinematics.point_jacobian, vectorised (segment i < j turns the point by L_i about
        the end of segment i and moves that end by its chord's derivative).
    """
    kappa = np.asarray(kappas, dtype=float)
    length = np.asarray(lengths, dtype=float)
    n_seg = len(length)
    joints = kinematics.forward(kappa, length, base)
    segment = np.repeat(np.arange(n_seg), per_segment)
    partial = length[segment] * np.tile(np.arange(1, per_segment + 1), n_seg) / per_segment
    start = joints[segment]
    chord, dchord = _chord(start[:, 2], kappa[segment], partial)
    points = start[:, :2] + chord
    # the last sample of each segment is its end: take forward()'s value, bit for bit
    points[per_segment - 1 :: per_segment] = joints[1:, :2]
    _, dfull = _chord(joints[:-1, 2], kappa, length)
    jacobian = np.zeros((len(points), 2, n_seg))
    for i in range(n_seg):
        distal = segment > i
        lever = points[distal] - joints[i + 1, :2]
        jacobian[distal, 0, i] = dfull[i, 0] - length[i] * lever[:, 1]
        jacobian[distal, 1, i] = dfull[i, 1] + length[i] * lever[:, 0]
        own = segment == i
        jacobian[own, :, i] = dchord[own]
    return points, jacobian


def _chord(heading: np.ndarray, kappa: np.ndarray, length: np.ndarray) -> tuple[np.ndarray, ...]:
    """Chord (end minus start) of arcs [m] and its derivative on the curvature [m^2]; see
    kinematics._chord_derivative (the same closed form and series, vectorised)."""
    half = 0.5 * kappa * length
    small = np.abs(half) < SMALL_HALF_ANGLE
    h = np.where(small, 1.0, half)  # a placeholder where the series is used
    h2 = half * half
    sinc = np.where(small, 1.0 - h2 / 6.0 * (1.0 - h2 / 20.0), np.sin(h) / h)
    dsinc = np.where(
        small,
        -half / 3.0 * (1.0 - h2 / 10.0 * (1.0 - h2 / 28.0)),
        (h * np.cos(h) - np.sin(h)) / (h * h),
    )
    direction = heading + half
    c, s = np.cos(direction), np.sin(direction)
    chord = np.stack((length * sinc * c, length * sinc * s), axis=-1)
    scale = 0.5 * length * length
    dchord = np.stack((scale * (dsinc * c - sinc * s), scale * (dsinc * s + sinc * c)), axis=-1)
    return chord, dchord


# ---------------------------------------------------------------------- planning


@dataclass(frozen=True)
class Plan:
    """A whole-arm plan: waypoints for the curvature controllers and how it went.

    Attributes
    ----------
    configurations
        Curvatures [1/m], each shape (N,), from the start (first) to the last waypoint.
    tip_path
        Tip position of each configuration, shape (len(configurations), 2) [m].
    clearance_min
        Smallest signed clearance [m] of any sampled backbone point (the capsule's axis) over
        all configurations: at least width / 2 means no penetration at the waypoints.
    reached
        Whether the last configuration puts the tip within the tolerance of the goal.
    reason
        Why the plan ended, one line.
    slack_steps
        Indices of the configurations whose clearance constraints could not be met and were
        relaxed (collisions tolerated); empty for a collision-free plan.
    """

    configurations: list[np.ndarray]
    tip_path: np.ndarray
    clearance_min: float
    reached: bool
    reason: str
    slack_steps: tuple[int, ...] = ()


@dataclass(frozen=True)
class _Problem:
    """What every step of one plan shares."""

    lengths: np.ndarray
    base: tuple[float, float, float]
    channel: Channel
    per_segment: int
    half_width: float  # [m] the capsule's radius
    required: float  # [m] clearance every sampled point must keep: width / 2 + margin
    lookahead: float  # [m]
    smoothness: float  # weight of the squared bend-angle change against (tip error / lookahead)^2

    def samples(self, kappa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return sample_backbone(kappa, self.lengths, self.base, self.per_segment)

    def clearance(self, kappa: np.ndarray) -> np.ndarray:
        return self.channel.clearance(self.samples(kappa)[0])

    def tip(self, kappa: np.ndarray) -> np.ndarray:
        return kinematics.forward(kappa, self.lengths, self.base)[-1, :2]


def plan_whole_arm(
    start: Floats,
    goal: Floats,
    lengths: Floats,
    base: tuple[float, float, float],
    lower: Floats,
    upper: Floats,
    channel: Channel,
    *,
    width: float = WIDTH,
    margin: float = 2e-3,
    samples_per_segment: int = 8,
    step: float = 2.0,
    max_steps: int = 300,
    tolerance: float = 1e-3,
    lookahead: float = 0.02,
    smoothness: float = 0.05,
    slack_penalty: float = 100.0,
) -> Plan:
    """Plan a sequence of curvature configurations that advances the tip to `goal` through
    `channel`, one constrained optimisation (SLSQP) per step; see the module.

    Parameters
    ----------
    start
        Starting curvatures, shape (N,) [1/m], within [lower, upper].
    goal
        Tip goal (x, y) [m].
    lengths, base
        Segment arc lengths, shape (N,) [m]; base pose (x [m], y [m], heading [rad]).
    lower, upper
        Curvature bounds per segment, shape (N,) [1/m].
    channel
        The walls and the centreline the tip follows.
    width
        Diameter of the arm's capsule [m].
    margin
        Clearance kept beyond width / 2 at every sampled point [m].
    samples_per_segment
        Backbone points per segment (the Environment FMU's n_samples).
    step
        Trust region: the largest change of any curvature between waypoints [1/m].
    max_steps
        Largest number of steps (waypoints after the start).
    tolerance
        Tip distance from the goal that counts as reached [m].
    lookahead
        How far ahead of the tip's progress along the centreline the step's target lies [m].
    smoothness
        Weight of the squared change of the bend angles [1/rad^2] against the squared tip
        error in units of `lookahead`.
    slack_penalty
        Weight of the squared slack [m] against the squared tip error (both in units of
        `lookahead`) when the clearance constraints are relaxed: the slack is what a step adds
        to the shortfall the body already has (a tolerated collision may persist at no cost,
        deepening it costs). Relaxed only when the constraints are infeasible or the feasible
        step does not advance the tip.

    Returns
    -------
    Plan
        Never raises for an unreachable or infeasible goal: `reached` is False and `reason`
        says why. Raises ValueError for inconsistent inputs (shapes, bounds, a start outside
        them).
    """
    lengths_ = np.asarray(lengths, dtype=float)
    kappa = np.asarray(start, dtype=float).copy()
    lo = np.broadcast_to(np.asarray(lower, dtype=float), lengths_.shape).copy()
    hi = np.broadcast_to(np.asarray(upper, dtype=float), lengths_.shape).copy()
    goal_ = np.asarray(goal, dtype=float)
    if kappa.shape != lengths_.shape:
        raise ValueError(f"start: {kappa.size} curvatures for {lengths_.size} segments")
    if np.any(lo > hi):
        raise ValueError("lower/upper: a lower curvature bound exceeds its upper bound")
    if np.any(kappa < lo - 1e-12) or np.any(kappa > hi + 1e-12):
        raise ValueError("start: a curvature lies outside [lower, upper]")
    if goal_.shape != (2,):
        raise ValueError(f"goal: expected (x, y), got shape {goal_.shape}")
    if step <= 0.0 or width <= 0.0 or margin < 0.0 or lookahead <= 0.0:
        raise ValueError("step, width and lookahead must be positive and margin not negative")
    kappa = np.clip(kappa, lo, hi)
    problem = _Problem(
        lengths_,
        base,
        channel,
        samples_per_segment,
        0.5 * width,
        0.5 * width + margin,
        lookahead,
        smoothness,
    )
    configurations = [kappa.copy()]
    slack_steps: list[int] = []

    def finish(reached: bool, reason: str) -> Plan:
        tips = np.array([problem.tip(k) for k in configurations])
        clearance = min(float(np.min(problem.clearance(k))) for k in configurations)
        return Plan(configurations, tips, clearance, reached, reason, tuple(slack_steps))

    goal_clearance = float(channel.clearance(goal_[None])[0])
    if goal_clearance < 0.5 * width:
        where = "outside the channel" if goal_clearance < 0.0 else "too close to a wall"
        return finish(
            False,
            f"goal ({goal_[0]:.4f}, {goal_[1]:.4f}) m lies {where}: clearance "
            f"{goal_clearance:.4f} m < half the width {0.5 * width:.4f} m",
        )
    goal_progress = float(channel.progress(goal_[None])[0])
    best = (math.inf, -math.inf)  # (distance to goal, progress) at the last real advance
    since_advance = 0
    for index in range(1, max_steps + 1):
        tip = problem.tip(kappa)
        distance = float(np.linalg.norm(tip - goal_))
        if distance <= tolerance:
            return finish(True, f"reached the goal within {distance * 1e3:.2f} mm")
        progress = float(channel.progress(tip[None])[0])
        if distance < best[0] - STALL_PROGRESS or progress > best[1] + STALL_PROGRESS:
            best = (min(distance, best[0]), max(progress, best[1]))
            since_advance = 0
        else:
            since_advance += 1
            if since_advance >= STALL_STEPS:
                return finish(
                    False,
                    f"stalled {distance * 1e3:.1f} mm from the goal, {progress:.3f} of "
                    f"{goal_progress:.3f} m along the centreline: the goal is out of reach",
                )
        target = _target(channel, tip, goal_, progress, goal_progress, lookahead)
        kappa_next, slack = _step(problem, kappa, target, lo, hi, step, slack_penalty)
        if slack:
            slack_steps.append(index)
        kappa = kappa_next
        configurations.append(kappa.copy())
    distance = float(np.linalg.norm(problem.tip(kappa) - goal_))
    if distance <= tolerance:
        return finish(True, f"reached the goal within {distance * 1e3:.2f} mm")
    return finish(False, f"max_steps = {max_steps} ran out {distance * 1e3:.1f} mm from the goal")


def plan_penetration(plan: Plan, width: float) -> float:
    """Deepest penetration [m] of the capsule of `width` into a wall at the plan's waypoints
    (zero for a plan whose clearance_min is at least width / 2)."""
    return max(0.0, 0.5 * width - plan.clearance_min)


def _target(
    channel: Channel,
    tip: np.ndarray,
    goal: np.ndarray,
    progress: float,
    goal_progress: float,
    lookahead: float,
) -> np.ndarray:
    """The step's target: the centreline point `lookahead` ahead of the tip's progress, or the
    goal once it is within the lookahead."""
    if goal_progress - progress <= lookahead or float(np.linalg.norm(goal - tip)) <= lookahead:
        return goal
    return channel.point_at(progress + lookahead)[0]


def _step(
    problem: _Problem,
    kappa: np.ndarray,
    target: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    step: float,
    slack_penalty: float,
) -> tuple[np.ndarray, bool]:
    """One waypoint: the constrained optimum within the trust region, the trust region halved
    until the linear interpolation from `kappa` keeps the body clear; (curvatures, slacked)."""
    before = float(np.min(problem.clearance(kappa)))
    radius = step
    for _ in range(MAX_HALVINGS + 1):
        candidate, slacked = _optimise(problem, kappa, target, lo, hi, radius, slack_penalty)
        # between waypoints no sampled point may come closer than the capsule's radius (the
        # margin is what the interpolation may use up), nor, after a tolerated collision,
        # deeper than the body already was
        floor = min(problem.half_width, before)
        if all(
            float(np.min(problem.clearance(kappa + f * (candidate - kappa)))) >= floor - FEASIBLE
            for f in INTERPOLATION_CHECKS
        ):
            break
        radius *= 0.5
    return candidate, slacked


def _optimise(
    problem: _Problem,
    kappa: np.ndarray,
    target: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    radius: float,
    slack_penalty: float,
) -> tuple[np.ndarray, bool]:
    """SLSQP within the trust region `radius` [1/m]; with a slack variable on the clearance
    constraints when they cannot be met. Returns (curvatures, slacked)."""
    n = len(kappa)
    lower = np.maximum(lo, kappa - radius)
    upper = np.minimum(hi, kappa + radius)
    scale = 1.0 / problem.lookahead**2
    weight = problem.smoothness * problem.lengths**2
    cache: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}

    def evaluate(k: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        key = k.tobytes()
        if key not in cache:
            points, jacobian = problem.samples(k)
            clearance, gradient = problem.channel.clearance_and_gradient(points)
            cache.clear()  # SLSQP asks for one point at a time
            cache[key] = (
                points[-1],
                jacobian[-1],
                clearance,
                np.einsum("pk,pkn->pn", gradient, jacobian),
            )
        return cache[key]

    def objective(x: np.ndarray) -> tuple[float, np.ndarray]:
        k = x[:n]
        tip, tip_jacobian, _, _ = evaluate(k)
        error = tip - target
        change = k - kappa
        value = scale * float(error @ error) + float(weight @ (change * change))
        gradient = np.zeros_like(x)
        gradient[:n] = 2.0 * scale * (tip_jacobian.T @ error) + 2.0 * weight * change
        if len(x) > n:
            value += slack_penalty * scale * x[n] ** 2
            gradient[n] = 2.0 * slack_penalty * scale * x[n]
        return value, gradient

    # a tolerated collision may stay as deep as it already is at no cost; the slack is what
    # the step adds to it
    shortfall = max(0.0, -float(np.min(evaluate(kappa)[2] - problem.required)))

    def constraint(x: np.ndarray) -> np.ndarray:
        return evaluate(x[:n])[2] - problem.required

    def relaxed_constraint(x: np.ndarray) -> np.ndarray:
        return constraint(x) + shortfall + x[n]

    def constraint_jacobian(x: np.ndarray) -> np.ndarray:
        jacobian = evaluate(x[:n])[3]
        if len(x) > n:
            jacobian = np.hstack((jacobian, np.ones((len(jacobian), 1))))
        return jacobian

    constraints = {"type": "ineq", "fun": constraint, "jac": constraint_jacobian}
    relaxed_constraints = {"type": "ineq", "fun": relaxed_constraint, "jac": constraint_jacobian}
    result = minimize(
        objective,
        kappa,
        jac=True,
        method="SLSQP",
        bounds=list(zip(lower, upper, strict=True)),
        constraints=[constraints],
        options={"maxiter": 100, "ftol": 1e-10},
    )
    candidate = np.clip(result.x, lower, upper)
    feasible = float(np.min(constraint(candidate))) >= -FEASIBLE
    distance = float(np.linalg.norm(evaluate(kappa)[0] - target))
    advance = distance - float(np.linalg.norm(evaluate(candidate)[0] - target))
    if feasible and (advance >= STALL_PROGRESS or distance <= STALL_PROGRESS):
        return candidate, False
    # infeasible, or feasible only by not advancing (the body kept clear of a pipe narrower
    # than width + 2 margin by staying out of it): tolerate the collision, as little of it as
    # the penalty buys
    result = minimize(
        objective,
        np.append(kappa, 0.0),
        jac=True,
        method="SLSQP",
        bounds=[*zip(lower, upper, strict=True), (0.0, None)],
        constraints=[relaxed_constraints],
        options={"maxiter": 100, "ftol": 1e-10},
    )
    relaxed = np.clip(result.x[:n], lower, upper)
    relaxed_advance = distance - float(np.linalg.norm(evaluate(relaxed)[0] - target))
    if feasible and relaxed_advance < advance + STALL_PROGRESS:
        return candidate, False  # the collision would buy no advance
    return relaxed, float(np.min(constraint(relaxed))) < -FEASIBLE


# ---------------------------------------------------------------------- the four pipe sections


@dataclass(frozen=True)
class PipeSection:
    """A shipped confined environment for the six-segment cylindrical-actuator arm.

    Attributes
    ----------
    name, description
        Scenario name (`planar-pipe-1` ...) and one line on what makes it hard.
    channel
        Walls (within the Environment FMU's capacity) and the centreline the tip follows.
    start
        Starting curvatures, shape (SEGMENTS,) [1/m]: the whole backbone inside the channel.
    goal
        Tip goal (x, y) [m], deep in the pipe.
    base
        Base pose (x [m], y [m], heading [rad]).
    """

    name: str
    description: str
    channel: Channel
    start: tuple[float, ...]
    goal: Point
    base: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def lengths(self) -> np.ndarray:
        """Segment lengths [m] of the arm the section is designed for."""
        return np.full(SEGMENTS, SEGMENT_LENGTH)


def _pipe_centreline(
    mouth: Point, pieces: Sequence[tuple[float, float]], max_turn: float
) -> np.ndarray:
    """Points of a pipe's centreline from `mouth` along +x: `pieces` of (arc length [m],
    curvature [1/m]), each arc cut into chords turning at most `max_turn` [rad]."""
    points = [np.array(mouth, dtype=float)]
    pose = (float(mouth[0]), float(mouth[1]), 0.0)
    for length, kappa in pieces:
        count = max(1, math.ceil(abs(kappa) * length / max_turn))
        for _ in range(count):
            pose = kinematics.segment_end(pose, kappa, length / count)
            points.append(np.array(pose[:2]))
    return np.array(points)


def _offset(line: np.ndarray, distance: float) -> list[Point]:
    """The polyline `line` offset by `distance` [m] to its left (miter joins)."""
    tangents = np.diff(line, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1)[:, None]
    normals = np.stack((-tangents[:, 1], tangents[:, 0]), axis=1)
    # at a joint the miter direction is the mean normal scaled so both edges keep the distance
    joint = normals[:-1] + normals[1:]
    joint /= np.sum(joint * normals[1:], axis=1)[:, None]
    offsets = np.vstack((normals[:1], joint, normals[-1:]))
    return [(float(x), float(y)) for x, y in line + distance * offsets]


def _section(
    name: str,
    description: str,
    *,
    mouth_x: float,
    bay: tuple[float, float],
    width: float,
    pieces: Sequence[tuple[float, float]],
    start: Sequence[float],
    goal_depth: float,
    max_turn: float = math.radians(15.0),
) -> PipeSection:
    """A bay (free space around the base, from x = -2 cm to the mouth, between y = bay[0] and
    bay[1]) opening at x = mouth_x into a pipe of `width` along `pieces` (see
    _pipe_centreline); the goal lies on the pipe's centreline `goal_depth` [m] past the mouth."""
    centre = _pipe_centreline((mouth_x, 0.0), pieces, max_turn)
    back = -0.02  # [m] the wall behind the base, with an opening the arm cannot reach
    left = [(back, 0.012), (back, bay[1]), (mouth_x, bay[1]), *_offset(centre, 0.5 * width)]
    right = [(back, -0.012), (back, bay[0]), (mouth_x, bay[0]), *_offset(centre, -0.5 * width)]
    line = np.vstack(([0.0, 0.0], centre))
    channel = Channel((tuple(left), tuple(right)), tuple(map(tuple, line)))
    goal_s = float(channel.progress(np.array([[mouth_x, 0.0]]))[0]) + goal_depth
    goal = channel.point_at(goal_s)[0]
    return PipeSection(
        name, description, channel, tuple(float(k) for k in start), (float(goal[0]), float(goal[1]))
    )


# the arm's start in every section: a bump of four bends in the bay (bend angles 0.95 rad, the
# tip at the mouth heading along the pipe) whose stored length the plan pays out into the pipe
_BUMP = (15.8, 0.0, -15.8, -15.8, 0.0, 15.8)
_BAY = (-0.04, 0.14)  # [m] the bay's lower and upper walls
_MOUTH_X = 0.25  # [m]


def _pipes() -> dict[str, PipeSection]:
    sections = (
        _section(
            "planar-pipe-1",
            "straight pipe 50 mm wide (17 mm of clearance each side of the arm)",
            mouth_x=_MOUTH_X,
            bay=_BAY,
            width=0.05,
            pieces=[(0.2, 0.0)],
            start=_BUMP,
            goal_depth=0.10,
        ),
        _section(
            "planar-pipe-2",
            "one left bend of 37 degrees (radius 125 mm) 20 mm past the mouth, 50 mm wide",
            mouth_x=_MOUTH_X,
            bay=_BAY,
            width=0.05,
            pieces=[(0.02, 0.0), (0.08, 8.0), (0.1, 0.0)],
            start=_BUMP,
            goal_depth=0.10,
        ),
        _section(
            "planar-pipe-3",
            "S-bend (23 degrees left then right, radius 100 mm) jogging 16 mm, 45 mm wide",
            mouth_x=_MOUTH_X,
            bay=_BAY,
            width=0.045,
            pieces=[(0.01, 0.0), (0.04, 10.0), (0.04, -10.0), (0.1, 0.0)],
            start=_BUMP,
            goal_depth=0.10,
        ),
        _section(
            "planar-pipe-4",
            "tight right bend of 83 degrees at radius 62 mm (curvature 16 of the arm's 20 1/m), "
            "40 mm wide: 12 mm of clearance each side",
            mouth_x=_MOUTH_X,
            bay=_BAY,
            width=0.04,
            pieces=[(0.01, 0.0), (0.09, -16.0), (0.1, 0.0)],
            start=_BUMP,
            goal_depth=0.10,
        ),
    )
    return {section.name: section for section in sections}


PIPES: dict[str, PipeSection] = _pipes()
"""The four shipped pipe sections by scenario name, in increasing difficulty. Each: a bay around
the base (from 20 mm behind it to the mouth 250 mm ahead, 40 mm below to 140 mm above the axis)
with the arm bent into a bump whose tip is at the mouth, and a pipe beyond; the goal is on the
pipe's centreline 100 mm past the mouth. For the six-segment 0.06 m arm of width 0.016 m with
curvatures within +-KAPPA_LIMIT."""
