"""Everything the spatial arm's controller knows of the arm: `ArmModel`.

The numbers are the ArmBody FMU's (fmus/ArmBody/model.toml, its README for their sources), under
the same names: per segment i (from the base) the arc length `L`, the rigid end pieces `L_p`, the
elastomer mass `mass` (uniform along the arc, lumped at `n_nodes` Gauss-Legendre nodes), the
endplate mass `m_end`, the bending stiffness `k` and damping `d`, the channels' volume change per
bend angle `G_a`; the bend limit `theta_max` (every segment); the gas circuits every pair shares
(isothermal, sealed at `p_atm` with the piston at `x_seal` and the arm straight); gravity in the
base frame; `planar` (one bending coordinate per segment, theta_y held at 0).

The plant side hands the FMU's parameter dict over (`ArmModel.from_fmu_parameters`, names as in
model.toml: `L_1`, `g_x`, ...); the controller's configuration ships it as JSON (`to_json`,
`from_json`). The defaults are ArmBody's (tests/test_spatial_model.py checks them against
model.toml): the default arm's base is horizontal, g = (-9.81, 0, 0) in the base frame, the
straight arm along the base's z axis.

Coordinates: q = (theta_x_1, theta_y_1, theta_x_2, ...), 2 N of them, or (theta_x_1, ...), N,
when `planar`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from functools import cached_property
from typing import Any

import numpy as np

MAX_SEGMENTS = 8
# ArmBody's per-segment defaults (segments 5-8 take the tip segment's values)
DEFAULT_SEGMENTS: dict[str, tuple[float, ...]] = {
    "L": (0.12, 0.11, 0.10, 0.09, 0.09, 0.09, 0.09, 0.09),
    "L_p": (0.005,) * 8,
    "mass": (0.16, 0.12, 0.09, 0.06, 0.06, 0.06, 0.06, 0.06),
    "m_end": (0.01,) * 8,
    "k": (0.8, 0.5, 0.3, 0.15, 0.15, 0.15, 0.15, 0.15),
    "d": (0.013, 0.008, 0.005, 0.0024, 0.0024, 0.0024, 0.0024, 0.0024),
    "G_a": (1.2e-5, 8e-6, 5e-6, 3e-6, 3e-6, 3e-6, 3e-6, 3e-6),
}
PER_SEGMENT = tuple(DEFAULT_SEGMENTS)
# ArmBody's scalar parameters the model carries, with their defaults
DEFAULT_SCALARS: dict[str, float] = {
    "theta_max": 1.6,
    "bore": 0.03175,
    "stroke": 0.1,
    "V_dead": 1e-5,
    "V_ch0": 5e-5,
    "C_a": 1e-10,
    "vacuum_factor": 0.5,
    "p_collapse": 3e4,
    "x_seal": 0.05,
    "p_atm": 101325.0,
}
DEFAULT_GRAVITY = (-9.81, 0.0, 0.0)
DEFAULT_N_SEGMENTS = 4
DEFAULT_N_NODES = 4
# ArmBody parameters and inputs that do not describe the arm the controller models (the start
# state, the integrator, the gas's temperature and constant, which cancel in an isothermal
# circuit sealed at p_atm), accepted and ignored by `from_fmu_parameters`
IGNORED_FMU_FAMILIES = (
    "theta_x_start",
    "theta_y_start",
    "x_piston_x",
    "x_piston_y",
    "tau_ext_x",
    "tau_ext_y",
)
IGNORED_FMU_SCALARS = ("substep", "T_gas", "R_gas")


@dataclass(frozen=True)
class ArmModel:
    """The arm's parameters in SI units (module docstring); per-segment tuples from the base."""

    L: tuple[float, ...] = DEFAULT_SEGMENTS["L"][:DEFAULT_N_SEGMENTS]
    L_p: tuple[float, ...] = DEFAULT_SEGMENTS["L_p"][:DEFAULT_N_SEGMENTS]
    mass: tuple[float, ...] = DEFAULT_SEGMENTS["mass"][:DEFAULT_N_SEGMENTS]
    m_end: tuple[float, ...] = DEFAULT_SEGMENTS["m_end"][:DEFAULT_N_SEGMENTS]
    k: tuple[float, ...] = DEFAULT_SEGMENTS["k"][:DEFAULT_N_SEGMENTS]
    d: tuple[float, ...] = DEFAULT_SEGMENTS["d"][:DEFAULT_N_SEGMENTS]
    G_a: tuple[float, ...] = DEFAULT_SEGMENTS["G_a"][:DEFAULT_N_SEGMENTS]
    theta_max: float = DEFAULT_SCALARS["theta_max"]
    n_nodes: int = DEFAULT_N_NODES
    gravity: tuple[float, float, float] = DEFAULT_GRAVITY
    planar: bool = False
    bore: float = DEFAULT_SCALARS["bore"]
    stroke: float = DEFAULT_SCALARS["stroke"]
    V_dead: float = DEFAULT_SCALARS["V_dead"]
    V_ch0: float = DEFAULT_SCALARS["V_ch0"]
    C_a: float = DEFAULT_SCALARS["C_a"]
    vacuum_factor: float = DEFAULT_SCALARS["vacuum_factor"]
    p_collapse: float = DEFAULT_SCALARS["p_collapse"]
    x_seal: float = DEFAULT_SCALARS["x_seal"]
    p_atm: float = DEFAULT_SCALARS["p_atm"]

    def __post_init__(self) -> None:
        for name in PER_SEGMENT:
            object.__setattr__(self, name, tuple(float(x) for x in getattr(self, name)))
        object.__setattr__(self, "gravity", tuple(float(x) for x in self.gravity))
        object.__setattr__(self, "planar", bool(self.planar))
        object.__setattr__(self, "n_nodes", _integer("n_nodes", self.n_nodes))
        self._validate()

    def _validate(self) -> None:
        n = len(self.L)
        if not 1 <= n <= MAX_SEGMENTS:
            raise ValueError(f"ArmModel: {n} segments (L), 1 to {MAX_SEGMENTS} expected")
        for name in PER_SEGMENT:
            values = getattr(self, name)
            if len(values) != n:
                raise ValueError(f"ArmModel.{name}: {len(values)} values for {n} segments")
            _check_range(name, values, strictly=name in ("L", "mass"))
        if len(self.gravity) != 3 or not all(map(math.isfinite, self.gravity)):
            raise ValueError(f"ArmModel.gravity: {self.gravity} is not a finite 3-vector")
        if not 1 <= self.n_nodes <= 8:
            raise ValueError(f"ArmModel.n_nodes: {self.n_nodes}, 1 to 8 expected")
        positive = ("theta_max", "bore", "stroke", "p_collapse", "p_atm")
        for name in DEFAULT_SCALARS:
            _check_range(name, (getattr(self, name),), strictly=name in positive)
        if not 0.0 <= self.vacuum_factor <= 1.0:
            raise ValueError(f"ArmModel.vacuum_factor: {self.vacuum_factor} outside [0, 1]")
        if self.x_seal > self.stroke:
            raise ValueError(
                f"ArmModel.x_seal: {self.x_seal} m outside the stroke [0, {self.stroke}]"
            )
        for i, G_a in enumerate(self.G_a):
            v_min = self.V_dead + self.V_ch0 - G_a * self.theta_max
            if not v_min > 0.0:
                raise ValueError(
                    f"ArmModel.G_a[{i}]: a gas volume can reach zero "
                    f"(V_dead + V_ch0 - G_a theta_max = {v_min:g} m^3)"
                )
            slope = G_a * (1.0 - self.vacuum_factor) * self.theta_max / self.p_collapse
            if self.p_atm * (slope - self.C_a) >= v_min:
                raise ValueError(
                    f"ArmModel.p_collapse: {self.p_collapse} Pa too sharp for G_a[{i}] (the "
                    "channel volume would not be monotone in pressure)"
                )

    # ------------------------------------------------------------------ sizes and derived

    @property
    def n_segments(self) -> int:
        return len(self.L)

    @property
    def n_dof(self) -> int:
        """Bending coordinates per segment: 1 planar, 2 spatial."""
        return 1 if self.planar else 2

    @property
    def n_q(self) -> int:
        return self.n_segments * self.n_dof

    @property
    def area(self) -> float:
        """Cylinder bore area [m^2]."""
        return 0.25 * math.pi * self.bore**2

    @cached_property
    def nodes(self) -> tuple[np.ndarray, np.ndarray]:
        """Gauss-Legendre nodes on [0, 1] (fractions of the arc) and their weights (sum 1)."""
        x, w = np.polynomial.legendre.leggauss(self.n_nodes)
        return 0.5 * (x + 1.0), 0.5 * w

    @cached_property
    def sealed_volume(self) -> np.ndarray:
        """Gas volume of side a and b at sealing (piston at x_seal, straight) [m^3]."""
        base = self.V_dead + self.V_ch0
        return np.array([self.area * (self.stroke - self.x_seal), self.area * self.x_seal]) + base

    @property
    def stiffness(self) -> np.ndarray:
        """Bending stiffness per coordinate [N m/rad], shape (n_q,)."""
        return np.repeat(np.asarray(self.k), self.n_dof)

    @property
    def g(self) -> np.ndarray:
        return np.asarray(self.gravity)

    @property
    def length(self) -> float:
        """The straight arm's length, end pieces included [m]."""
        return float(sum(self.L) + 2.0 * sum(self.L_p))

    @property
    def total_mass(self) -> float:
        return float(sum(self.mass) + sum(self.m_end))

    def full(self, q: np.ndarray) -> np.ndarray:
        """q (..., n_q) as (..., N, 2) (theta_x, theta_y) per segment (theta_y 0 when planar)."""
        q = np.asarray(q)
        if q.shape[-1] != self.n_q:
            raise ValueError(f"q has {q.shape[-1]} coordinates, the arm {self.n_q}")
        if not self.planar:
            return q.reshape(*q.shape[:-1], self.n_segments, 2)
        out = np.zeros((*q.shape, 2), dtype=q.dtype)
        out[..., 0] = q
        return out

    def reduce(self, full: np.ndarray) -> np.ndarray:
        """The inverse of `full` on the last two axes (N, 2) -> n_q (planar: theta_x only)."""
        full = np.asarray(full)
        if self.planar:
            return full[..., 0]
        return full.reshape(*full.shape[:-2], self.n_q)

    def bend_angles(self, q: np.ndarray) -> np.ndarray:
        """|theta_i| per segment, shape (..., N)."""
        return np.linalg.norm(self.full(q), axis=-1)

    # ------------------------------------------------------------------ conversions

    @classmethod
    def from_fmu_parameters(cls, parameters: Mapping[str, float]) -> ArmModel:
        """The arm of an ArmBody FMU with these parameter values (model.toml's names; any not
        given takes ArmBody's default). Start states, inputs, `substep`, `T_gas` and `R_gas` are
        accepted and ignored; `gas = 0` (no gas torque) and unknown names are refused."""
        n = _integer("n_segments", parameters.get("n_segments", DEFAULT_N_SEGMENTS))
        if not 1 <= n <= MAX_SEGMENTS:
            raise ValueError(f"ArmBody parameter n_segments = {n}: 1 to {MAX_SEGMENTS} expected")
        if "gas" in parameters and not parameters["gas"]:
            raise ValueError("ArmBody parameter gas = 0: the controller's model needs the gas")
        _check_names(parameters)
        values: dict[str, Any] = {
            name: tuple(
                float(parameters.get(f"{name}_{i + 1}", DEFAULT_SEGMENTS[name][i]))
                for i in range(n)
            )
            for name in PER_SEGMENT
        }
        for name, default in DEFAULT_SCALARS.items():
            values[name] = float(parameters.get(name, default))
        values["n_nodes"] = _integer("n_nodes", parameters.get("n_nodes", DEFAULT_N_NODES))
        values["gravity"] = tuple(
            float(parameters.get(f"g_{axis}", default))
            for axis, default in zip("xyz", DEFAULT_GRAVITY, strict=True)
        )
        values["planar"] = bool(_integer("planar", parameters.get("planar", 0)))
        return cls(**values)

    def to_fmu_parameters(self) -> dict[str, float]:
        """The ArmBody parameters of this arm (per-segment families for its segments only)."""
        out: dict[str, float] = {
            "n_segments": self.n_segments,
            "planar": int(self.planar),
            "n_nodes": self.n_nodes,
        }
        for name in PER_SEGMENT:
            for i, value in enumerate(getattr(self, name)):
                out[f"{name}_{i + 1}"] = value
        for name in DEFAULT_SCALARS:
            out[name] = getattr(self, name)
        for axis, value in zip("xyz", self.gravity, strict=True):
            out[f"g_{axis}"] = value
        return out

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ArmModel:
        """The model `to_json` wrote; a missing field takes its default, an unknown one fails."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise ValueError(f"ArmModel JSON: {error}") from None
        if not isinstance(data, dict):
            raise ValueError("ArmModel JSON: an object expected")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"ArmModel JSON: unknown key {unknown[0]!r}")
        for name in (*PER_SEGMENT, "gravity"):
            if name in data and not isinstance(data[name], list):
                raise ValueError(f"ArmModel JSON: {name!r} must be a list")
        values: dict[str, Any] = {
            name: tuple(v) if isinstance(v, list) else v for name, v in data.items()
        }
        return cls(**values)


def _integer(name: str, value: Any) -> int:
    if isinstance(value, bool) or float(value) != int(value):
        raise ValueError(f"ArmModel.{name}: {value!r} is not an integer")
    return int(value)


def _check_range(name: str, values: tuple[float, ...], strictly: bool) -> None:
    for i, value in enumerate(values):
        bad = not math.isfinite(value) or (value <= 0.0 if strictly else value < 0.0)
        if bad:
            where = f"{name}[{i}]" if len(values) > 1 or name in PER_SEGMENT else name
            sign = "positive" if strictly else "non-negative"
            raise ValueError(f"ArmModel.{where}: {value!r}, a finite {sign} number expected")


def _check_names(parameters: Mapping[str, float]) -> None:
    scalars = {*DEFAULT_SCALARS, "n_segments", "planar", "gas", "n_nodes", "g_x", "g_y", "g_z"}
    scalars.update(IGNORED_FMU_SCALARS)
    families = (*PER_SEGMENT, *IGNORED_FMU_FAMILIES)
    for name in parameters:
        family, _, index = name.rpartition("_")
        member = family in families and index.isdigit() and 1 <= int(index) <= MAX_SEGMENTS
        if name not in scalars and not member:
            raise ValueError(f"ArmBody parameter {name!r} is unknown to the arm's model")
