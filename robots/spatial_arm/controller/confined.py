"""The spatial arm in a confined space: entering a pipe and advancing its tip to a goal inside it
with the arm kept off the wall, and the minimum confining space the arm needs against a
rigid-link arm of the same reach.

The pipe is a polyline centreline `axis` (its first point the entrance) and a `radius`; the arm
is `width` wide. Plan (`plan_insertion`): the tip first goes to points ENTRY_STANDOFFS before the
entrance on the axis's line, then advances along the axis in steps of at most `step` to the
goal depth. Each station's bends solve, from the previous station's, min |q - q_prev|^2 with
the tip on the axis at that depth (an equality) and the arm's inserted part, and LEAD of arm
behind it, within `radius - width / 2 - clearance` of the axis or of its line before the
entrance (inequalities: the arm follows its tip in), under the static
constraints (ik.constraints: every pair's torque within its stroke, the bend limit): the arm
follows its tip into the pipe as far as its statics allow. Between stations the controller moves
along straight lines in bend space, short enough (`step`) that the arm stays near the planned
corridor; the metrics measure what the true arm did.

Minimum confining space (`confining_radius`): the smallest pipe radius around a circular axis of
bend radius R that holds the arm's length inside it. The soft arm bends continuously: its best
fit to the arc (ik.fit_shape, without gravity: the geometry alone) leaves a residual, plus half
its width. A rigid-link arm of the same reach (one straight link per segment, end pieces
included, joints at the endplates) can at best put its joints on the axis, and each straight
link then leaves the arc by its sagitta R - sqrt(R^2 - l^2 / 4): the rigid arm needs that plus
half its width.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import minimize

from robots.spatial_arm.controller import ik
from robots.spatial_arm.controller.kinematics import Stations, points, stations, tip_jacobian
from robots.spatial_arm.controller.model import ArmModel

ENTRY_STANDOFFS = (0.06, 0.02)  # [m] approach stations before the entrance on the axis's line
LEAD = 0.02  # [m] of the arm behind the inserted part also kept on the axis's line
POINTS_PER_SEGMENT = 6
MAX_ITERATIONS = 200


@dataclass(frozen=True)
class Pipe:
    axis: np.ndarray  # (K, 3) the centreline from the entrance [m]
    radius: float  # [m]

    def extended(self, back: float) -> Pipe:
        """The same pipe with its axis prolonged `back` [m] before the entrance (the line the arm
        approaches along)."""
        a = np.asarray(self.axis, dtype=float)
        u = (a[1] - a[0]) / np.linalg.norm(a[1] - a[0])
        return Pipe(np.vstack([a[0] - back * u, a]), self.radius)

    def along(self, depth: float) -> np.ndarray:
        """The axis point `depth` [m] past the entrance (before it: on the first piece's
        extension)."""
        a = np.asarray(self.axis, dtype=float)
        pieces = np.diff(a, axis=0)
        lengths = np.linalg.norm(pieces, axis=1)
        if depth <= 0.0:
            return a[0] + depth * pieces[0] / lengths[0]
        s = np.concatenate([[0.0], np.cumsum(lengths)])
        k = min(int(np.searchsorted(s, depth, side="right")) - 1, len(pieces) - 1)
        return a[k] + (depth - s[k]) * pieces[k] / lengths[k]

    @property
    def length(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.axis, axis=0), axis=1)))

    def distance(self, p: np.ndarray) -> np.ndarray:
        """Each point's distance from the axis (..., 3) -> (...) [m]."""
        a = np.asarray(self.axis, dtype=float)
        start, piece = a[:-1], np.diff(a, axis=0)
        rel = p[..., None, :] - start
        s = np.clip(np.einsum("...ki,ki->...k", rel, piece) / np.sum(piece * piece, axis=1), 0, 1)
        nearest = start + s[..., None] * piece
        return np.asarray(np.min(np.linalg.norm(p[..., None, :] - nearest, axis=-1), axis=-1))

    def depth(self, p: np.ndarray) -> np.ndarray:
        """How far past the entrance plane each point is, along the first piece [m]."""
        a = np.asarray(self.axis, dtype=float)
        u = (a[1] - a[0]) / np.linalg.norm(a[1] - a[0])
        return np.asarray((p - a[0]) @ u)


def arm_stations(model: ArmModel) -> Stations:
    return stations(model, POINTS_PER_SEGMENT)


def _inside_constraint(
    model: ArmModel, pipe: Pipe, room: float, where: Stations, past: np.ndarray
) -> dict:
    """room - distance from the axis >= 0 for the stations `past` the entrance (their arc
    length from the tip below the insertion depth)."""
    chosen = Stations(where.segment[past], where.xi[past], where.arc_length[past])

    def fun(q: np.ndarray) -> np.ndarray:
        p, _ = points(model, q, chosen)
        return room - pipe.distance(p)

    def jac(q: np.ndarray) -> np.ndarray:
        p, J = points(model, q, chosen, jacobian=True)
        assert J is not None
        h = 1e-7
        grad = np.empty((len(p), 3))
        for k in range(3):  # d distance / d p along each axis (the distance is piecewise smooth)
            dp = np.zeros(3)
            dp[k] = h
            grad[:, k] = (pipe.distance(p + dp) - pipe.distance(p - dp)) / (2 * h)
        return -np.einsum("pi,pin->pn", grad, J)

    return {"type": "ineq", "fun": fun, "jac": jac}


def station(
    model: ArmModel, pipe: Pipe, depth: float, room: float, q_prev: np.ndarray, margin: float
) -> tuple[np.ndarray, float]:
    """The bends with the tip `depth` past the entrance, the inserted part inside `room` of the
    axis, nearest q_prev; and how far the tip ended from its target [m]."""
    where = arm_stations(model)
    length = float(where.arc_length[-1])
    # the inserted part and LEAD behind it, on the axis or its line before the entrance
    past = where.arc_length >= length - max(depth + LEAD, 0.0) + 1e-9
    target = pipe.along(depth)

    def objective(q: np.ndarray) -> tuple[float, np.ndarray]:
        d = q - q_prev
        return float(d @ d), 2.0 * d

    def on_target(q: np.ndarray) -> np.ndarray:
        return (tip_jacobian(model, q)[0] - target) / model.length

    def on_target_jac(q: np.ndarray) -> np.ndarray:
        return tip_jacobian(model, q)[1] / model.length

    cons = [{"type": "eq", "fun": on_target, "jac": on_target_jac}, *ik.constraints(model, margin)]
    if past.any():
        line = pipe.extended(max(ENTRY_STANDOFFS) + LEAD + model.length)
        cons.append(_inside_constraint(model, line, room, where, past))
    start = ik.solve_ik(model, target, start=q_prev, prefer=q_prev, margin=margin).q
    result = minimize(
        objective,
        start,
        jac=True,
        method="SLSQP",
        constraints=cons,
        options={"maxiter": MAX_ITERATIONS, "ftol": 1e-10},
    )
    q = np.asarray(result.x)
    return q, float(np.linalg.norm(tip_jacobian(model, q)[0] - target))


def plan_insertion(
    model: ArmModel,
    pipe: Pipe,
    goal_depth: float,
    width: float,
    clearance: float,
    step: float,
    q_start: np.ndarray,
    margin: float = ik.MARGIN,
) -> list[np.ndarray]:
    """The stations' bends: the standoff before the entrance, then every `step` to the goal."""
    room = pipe.radius - 0.5 * width - clearance
    if room <= 0.0:
        raise ValueError(
            f"the pipe's radius {pipe.radius:g} m leaves no room for the arm's {width:g} m "
            f"width and {clearance:g} m clearance"
        )
    depths = [-d for d in ENTRY_STANDOFFS] + [*np.arange(step, goal_depth, step), goal_depth]
    plan, q = [], np.asarray(q_start, dtype=float)
    for depth in depths:
        q, _ = station(model, pipe, float(depth), room, q, margin)
        plan.append(q)
    return plan


# ------------------------------------------------------------------ the confining space


def arc(radius: float, length: float, n: int = 200) -> np.ndarray:
    """A circular axis from the base along +z bending towards +x, of the given length."""
    phi = np.linspace(0.0, length / radius, n)
    return np.column_stack([radius * (1.0 - np.cos(phi)), np.zeros(n), radius * np.sin(phi)])


def link_lengths(model: ArmModel) -> np.ndarray:
    """The rigid-link arm of the same reach: one straight link per segment, end pieces included."""
    return np.asarray(model.L) + 2.0 * np.asarray(model.L_p)


def rigid_confining_radius(model: ArmModel, bend_radius: float, width: float) -> float:
    """Joints on the arc: the largest link's sagitta plus half the width [m]."""
    longest = float(np.max(link_lengths(model)))
    if longest >= 2.0 * bend_radius:
        return float("inf")
    return bend_radius - float(np.sqrt(bend_radius**2 - 0.25 * longest**2)) + 0.5 * width


def soft_confining_radius(model: ArmModel, bend_radius: float, width: float) -> float:
    """The soft arm's best fit to the arc (geometry alone: no gravity, no stroke limits): its
    largest distance from the arc plus half the width [m]."""
    weightless = replace(model, gravity=(0.0, 0.0, 0.0))
    curve = arc(bend_radius, float(np.sum(link_lengths(model))))
    fit = ik.fit_shape(weightless, curve, margin=0.0)
    line = points(weightless, fit.q, arm_stations(weightless))[0]
    axis = Pipe(curve, bend_radius)
    return float(np.max(axis.distance(line))) + 0.5 * width


def confining_table(
    model: ArmModel, bend_radii: np.ndarray, width: float
) -> list[tuple[float, float, float]]:
    """(bend radius, soft arm's, rigid arm's minimum confining radius) [m] for each."""
    return [
        (float(R), soft_confining_radius(model, R, width), rigid_confining_radius(model, R, width))
        for R in bend_radii
    ]
