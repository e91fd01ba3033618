"""The confined spaces of the planar arm (issue 12): a planar `Channel`
(walls, the centreline the tip follows, the signed clearance of any point) and the four shipped
pipe sections (`PIPES`) of the thesis's confined-space experiments, for its six-segment
"cylindrical actuator" arm. Planning the whole arm through a channel is
robots.planar_arm.controller.confined_planner's.

The channel's walls are what the Environment FMU takes (at most 2 polylines of 16 vertices).
Invariant: a Channel is checked when it is made (within the FMU's capacity, finite, its region a
simple polygon), and its clearance is zero on the walls, positive inside and negative outside.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from controllers import kinematics

Point = tuple[float, float]

MAX_WALLS = 2  # the Environment FMU's capacity
MAX_VERTICES = 16

# the "cylindrical actuator" arm of the thesis's confined-space experiments [estimate]
SEGMENTS = 6
SEGMENT_LENGTH = 0.06  # [m]
WIDTH = 0.016  # [m] diameter of the cylindrical actuator
KAPPA_LIMIT = 20.0  # [1/m] planning bound of each curvature (radius 5 cm)


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
