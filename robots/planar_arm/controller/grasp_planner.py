"""Grasp-and-place planning of the planar arm with its soft gripper (issue 12).

The thesis's planar grasping manipulator approaches a randomly placed object along "concentric
approach circles" that shrink onto it, the gripper facing the object's centre, without touching
it; it then grasps the object, carries it to a place location and releases it. This module plans
those moves for the controller (robots.planar_arm.controller.grasp_control): pure planning on the
arm's curvatures, no plant state.

- `plan_approach`: arm configurations whose tip poses lie on circles of standoff rho_k around the
  object centre (the tip at `tip_for_grasp(centre, heading, standoff=rho_k)`), rho_k shrinking to
  0 (the grasp pose). The approach heading is chosen among those at which every circle is
  reachable (heading-constrained IK) and every move is clear, by the shortest motion; the
  gripper then goes radially inwards at that one heading. (Entering the outer circle at another
  heading and going round it was tried and dropped: of 80 random starts with the object 3 to
  10 mm beside the arm's body, it rescued none of the 14 that found no clear approach; where
  the move onto the outer circle sweeps through the object at every heading, so does any other
  first move.)
- `plan_retreat`: after release, the open gripper backed off along its axis to the outer radius.

The carry between them (the object in the hand) is robots.planar_arm.controller.grasp_carry's.

"Without touching": every waypoint and every point of the straight curvature interpolation
between consecutive waypoints (what `robots.planar_arm.controller.tasks.CurvatureMove` tracks)
keeps the open fingers and the arm's backbone at least `margin` from the object's disk, by the
guaranteed bound of robots.planar_arm.controller.grasp_clearance. Where an interpolation is not
clear, the move is split at the middle pose (on the same radial line), solved by IK
warm-started from its neighbour, up to MAX_SPLITS times.

Invariant: every returned configuration lies within [lower, upper] and meets its tip pose by the
IK's tolerance; consecutive configurations come from warm-started IK; `GraspPlan.clearance` is a
lower bound of the clearance along the whole plan (start included) and is >= margin for the
approach and the retreat; every function is deterministic.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from controllers import kinematics
from robots.planar_arm.controller.grasp_clearance import (
    ARM_WIDTH,
    BODY_SAMPLES,
    Floats,
    Pose,
    sweep_clearance,
)
from robots.planar_arm.controller.gripper import (
    GripperGeometry,
    finger_points,
    tip_for_grasp,
)
from robots.planar_arm.controller.ik import solve_ik

MARGIN = 1.5e-3  # [m] clearance kept between the object and the gripper or arm
CIRCLES = 4  # approach circles, the grasp pose (radius 0) included
HEADING_STEP = math.radians(10.0)  # [rad] grid of approach headings, and the step along a circle
MAX_SPLITS = 4  # halvings of one move before the interpolation check gives up on it
SEARCH_ITERATIONS = 25  # IK iterations of a warm-started solve (they meet the pose in < 15)


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


@dataclass(frozen=True)
class Arm:
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
    ) -> Arm:
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


def _waypoint(arm: Arm, centre: Floats, node: _Node) -> tuple[np.ndarray, Pose]:
    x, y, h = tip_for_grasp(
        arm.geometry, (float(centre[0]), float(centre[1])), node.heading, node.standoff
    )
    actual = float(arm.tip(node.kappas)[2])
    return node.kappas, (x, y, actual + math.remainder(h - actual, 2.0 * math.pi))


def _sweep(arm: Arm, obstacle: _Obstacle, a: np.ndarray, b: np.ndarray) -> float:
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
    arm: Arm, obstacle: _Obstacle, a: _Node, b: _Node, splits: int = MAX_SPLITS
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
    arm: Arm, obstacle: _Obstacle, start: np.ndarray, nodes: Sequence[_Node]
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


def headings_around(
    arm: Arm, centre: Floats, standoff: float, heading: float, kappas: np.ndarray
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


def _check_object(arm: Arm, obstacle: _Obstacle, current: np.ndarray, what: str) -> None:
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
    arm = Arm.of(lengths, base, lower, upper, geometry, width)
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
    grasps = list(headings_around(arm, centre, 0.0, float(arm.tip(seed)[2]), seed))
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
    arm: Arm,
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
    arm: Arm,
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
    arm = Arm.of(lengths, base, lower, upper, geometry, width)
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
