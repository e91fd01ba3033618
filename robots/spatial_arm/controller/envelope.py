"""The arm's statically reachable envelope: where its tip can rest under gravity.

`sample_envelope` draws piston settings uniformly in [margin, stroke - margin] per pair (seeded:
the same seed gives the same envelope bit for bit), solves each setting's static equilibrium
(equilibrium.py: vectorised Newton over the whole batch from the straight arm, the bend limit
included) and keeps the tips of the stable rests, with their bends and pistons.

Inside test (`Envelope.contains`): a goal is inside when it lies within the convex hull of the
sampled tips, at least `margin` from every hull facet, AND within `radius` of a sampled tip.
Why both: the reachable set is the image of the pistons' 2N-cube under the nonlinear statics, a
solid that need not be convex (the arm cannot fold its tip back into the base, for one); the
hull alone accepts goals in such dents, nearness alone accepts goals up to `radius` beyond the
true boundary wherever the samples reach it. Together a goal must sit in the hull and next to
an actually reached rest; a dent narrower than `radius` is still accepted. `radius` comes from the
samples' own spacing (RADIUS_FACTOR times the RADIUS_PERCENTILE-th percentile of each tip's
distance to its nearest neighbour), so it shrinks as the sampling grows denser. An alpha shape
would follow the dents without the second test but needs its own radius choice and a mesh
library; scipy's Qhull hull and k-d tree are enough here.

`draw_goals` draws goals uniformly in the samples' bounding box and keeps those `contains`
accepts (rejection sampling, reproducible from the caller's numpy Generator). `start_for` gives
the bends of the sampled rest nearest a goal: a start for ik.solve_ik that sits in the right
basin. Export: `save` to .npz (everything) or .csv (the tips, header x,y,z); `load` reads both
(a .csv gives the tips alone).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from robots.spatial_arm.controller.equilibrium import static_equilibrium
from robots.spatial_arm.controller.kinematics import tip
from robots.spatial_arm.controller.model import ArmModel

RADIUS_FACTOR = 2.0
RADIUS_PERCENTILE = 95.0
HULL_ROUNDING = 1e-12  # [m] a hull vertex's own depth is zero within rounding
CHUNK = 1000  # piston settings solved together
DRAW_BATCH = 256
DRAW_ROUNDS = 1000


def default_radius(points: np.ndarray) -> float:
    """RADIUS_FACTOR times the RADIUS_PERCENTILE-th percentile of nearest-neighbour distances."""
    distance, _ = cKDTree(points).query(points, k=2)
    return float(RADIUS_FACTOR * np.percentile(distance[:, 1], RADIUS_PERCENTILE))


@dataclass(frozen=True, eq=False)
class Envelope:
    """Sampled rest positions of the tip (M, 3) [m] with the inside test's `radius` [m], and
    (when known) the bends (M, n_q) and pistons (M, n_q) [m] of each."""

    points: np.ndarray
    radius: float
    q: np.ndarray | None = None
    pistons: np.ndarray | None = None

    def __post_init__(self) -> None:
        points = np.asarray(self.points, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 5:
            raise ValueError(f"Envelope: points of shape {points.shape}, (M >= 5, 3) expected")
        if not np.all(np.isfinite(points)):
            raise ValueError("Envelope: the points are not all finite")
        if not self.radius > 0.0:
            raise ValueError(f"Envelope: radius {self.radius} is not positive")
        for name in ("q", "pistons"):
            value = getattr(self, name)
            if value is not None and len(value) != len(points):
                raise ValueError(f"Envelope.{name}: {len(value)} rows for {len(points)} points")
        object.__setattr__(self, "points", points)

    @classmethod
    def from_points(cls, points: np.ndarray, **known: np.ndarray) -> Envelope:
        """The envelope of these tips with the default radius."""
        points = np.asarray(points, dtype=float)
        return cls(points=points, radius=default_radius(points), **known)

    @cached_property
    def hull(self) -> ConvexHull:
        return ConvexHull(self.points)

    @cached_property
    def tree(self) -> cKDTree:
        return cKDTree(self.points)

    def hull_depth(self, goals: np.ndarray) -> np.ndarray:
        """Distance inside the hull's nearest facet plane [m] (negative outside), (...)."""
        goals = np.asarray(goals, dtype=float)
        eq = self.hull.equations  # unit normals: n . p + offset <= 0 inside
        return -np.max(goals @ eq[:, :3].T + eq[:, 3], axis=-1)

    def nearest(self, goals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance to the nearest sampled tip [m] and its index, (...) each."""
        distance, index = self.tree.query(np.asarray(goals, dtype=float))
        return np.asarray(distance), np.asarray(index)

    def contains(self, goals: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Inside the hull by at least `margin` [m] and within `radius` of a sampled tip."""
        distance, _ = self.nearest(goals)
        return (self.hull_depth(goals) >= margin - HULL_ROUNDING) & (distance <= self.radius)

    def draw_goals(self, rng: np.random.Generator, n: int, margin: float = 0.0) -> np.ndarray:
        """n goals (n, 3) drawn uniformly in the bounding box among those `contains` accepts."""
        lo, hi = self.points.min(axis=0), self.points.max(axis=0)
        found: list[np.ndarray] = []
        count = 0
        for _ in range(DRAW_ROUNDS):
            if count >= n:
                break
            candidates = rng.uniform(lo, hi, size=(DRAW_BATCH, 3))
            kept = candidates[self.contains(candidates, margin)]
            found.append(kept)
            count += len(kept)
        else:
            raise ValueError(f"draw_goals: margin {margin} m leaves too little of the envelope")
        return np.concatenate(found)[:n]

    def start_for(self, goal: np.ndarray) -> np.ndarray:
        """The bends of the sampled rest whose tip is nearest the goal."""
        if self.q is None:
            raise ValueError(
                "Envelope.start_for: this envelope carries no bends (loaded from .csv)"
            )
        _, index = self.nearest(goal)
        return np.asarray(self.q[index])

    def save(self, path: str | Path) -> None:
        """To .npz (points, radius, q and pistons when known) or .csv (points, header x,y,z)."""
        path = Path(path)
        if path.suffix == ".csv":
            np.savetxt(path, self.points, delimiter=",", header="x,y,z", comments="", fmt="%.17g")
        elif path.suffix == ".npz":
            arrays: dict[str, Any] = {"points": self.points, "radius": np.array(self.radius)}
            arrays.update(
                {k: v for k, v in (("q", self.q), ("pistons", self.pistons)) if v is not None}
            )
            np.savez(path, **arrays)
        else:
            raise ValueError(f"{path}: an envelope is saved as .npz or .csv")

    @classmethod
    def load(cls, path: str | Path) -> Envelope:
        """What `save` wrote (a .csv's radius is the default one of its points)."""
        path = Path(path)
        if path.suffix == ".csv":
            with open(path, encoding="utf-8") as file:
                header = file.readline().strip()
            if header != "x,y,z":
                raise ValueError(f"{path}: header {header!r}, 'x,y,z' expected")
            points = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
            return cls.from_points(points)
        if path.suffix != ".npz":
            raise ValueError(f"{path}: an envelope is loaded from .npz or .csv")
        with np.load(path) as data:
            for key in ("points", "radius"):
                if key not in data:
                    raise ValueError(f"{path}: no {key!r} array")
            known = {k: np.array(data[k]) for k in ("q", "pistons") if k in data}
            return cls(points=np.array(data["points"]), radius=float(data["radius"]), **known)


def sample_envelope(model: ArmModel, n: int = 3000, seed: int = 0, margin: float = 0.0) -> Envelope:
    """The tips of the stable rests at n piston settings drawn uniformly (seeded) in [margin,
    stroke - margin] per pair: module docstring."""
    if not 0.0 <= margin < 0.5 * model.stroke:
        raise ValueError(f"margin = {margin} m: outside [0, stroke / 2)")
    rng = np.random.default_rng(seed)
    pistons = rng.uniform(margin, model.stroke - margin, size=(n, model.n_q))
    q = np.empty_like(pistons)
    ok = np.empty(n, dtype=bool)
    for start in range(0, n, CHUNK):
        rest = static_equilibrium(model, pistons[start : start + CHUNK])
        q[start : start + CHUNK] = rest.q
        ok[start : start + CHUNK] = rest.ok
    return Envelope.from_points(tip(model, q[ok]), q=q[ok], pistons=pistons[ok])
