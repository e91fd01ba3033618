"""The planar arm as one multibody ArmBody FMU (`robot.model = "body"`, the default): the inertia
each segment carries, the whole outer arm's for the base, and the inertial coupling between the
segments, which the per-segment FeaSegment FMUs (`robot.model = "segments"`) leave out.

The scenario's segments are resolved as FeaSegment parameters (`[robot.segment]`, the actuator's
parameter set, FeaSegment's defaults) and mapped onto ArmBody's (`values`): per segment i,
L_i = length, mass_i = mass, k_i = k_bend, d_i = d_bend, G_a_i = G_a, theta_x_start_i =
theta_start; L_p_i = 0 and m_end_i = 0, because a FeaSegment has no rigid end pieces and its
`mass` is the whole segment's, spread along its arc (its inertia m L^2 / 20 says so): the arc's
mass alone, with no endplate, is the same segment. ArmBody's one bend limit and one gas circuit
serve every segment: theta_max, V_dead, V_ch0, C_a, vacuum_factor, p_collapse, p_atm, T_gas,
R_gas and the cylinders' bore, stroke and x_start (where the circuits were sealed) must be alike
over the segments, else the scenario fails naming the first key that differs (robot.model =
"segments" takes them per segment). ArmBody's circuits are isothermal and sealed: n_poly > 1 and
a leak_conductance are refused (tau_thermal acts only with n_poly > 1); FeaSegment's `substep`
is refused too, the body taking the largest substep its stability limit allows (ArmBody's
substep = 0).

Gravity: the arm lies on the table with its bending plane (the body's x-z plane) horizontal, so
gravity is along the body's y axis, normal to that plane: g = (0, -9.81, 0) gives no torque on
any bend (the table carries the weight; its friction is the Environment FMU's).

Wiring per segment n: cylinder{n}.x -> body.x_piston_x_n, body.p_a_x_n / p_b_x_n -> cylinder{n}
and drive{n}, body.kappa_x_n (signed) -> camera.kappa_n, and with an Environment FMU the signed
curvature and bend rate in, its torque out to body.tau_ext_x_n.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from hil.scenario import Scenario

FMU = "ArmBody"
NAME = "body"  # the participant
MODELS = ("body", "segments")
GRAVITY = -9.81  # [m/s^2] along the body's y axis, the table's normal: no torque in the plane
# FeaSegment parameter -> ArmBody family (NAME_i)
PER_SEGMENT = {
    "length": "L",
    "mass": "mass",
    "k_bend": "k",
    "d_bend": "d",
    "G_a": "G_a",
    "theta_start": "theta_x_start",
}
# FeaSegment parameters ArmBody shares over all segments (same names)
SHARED_SEGMENT = (
    "theta_max",
    "V_dead",
    "V_ch0",
    "C_a",
    "vacuum_factor",
    "p_collapse",
    "p_atm",
    "T_gas",
    "R_gas",
)
# the cylinders' geometry the gas circuits take: DriveCylinder parameter -> ArmBody parameter
SHARED_CYLINDER = {"bore": "bore", "stroke": "stroke", "x_start": "x_seal"}
# FeaSegment features ArmBody has not: (parameter, the value ArmBody models, why refused)
REFUSED = (
    ("n_poly", 1.0, "the body's gas circuits are isothermal"),
    ("leak_conductance", 0.0, "the body's gas circuits are sealed"),
)
IGNORED = ("tau_thermal",)  # acts only with n_poly > 1


def present(scenario: Scenario) -> bool:
    """Whether the arm is one ArmBody (robot.model = "body")."""
    return getattr(scenario.robot, "model", "segments") == "body"


def check(
    scenario: Scenario,
    given: Sequence[Mapping[str, tuple[float, str]]],
    segments: Sequence[Mapping[str, float]],
    cylinders: Sequence[Mapping[str, float]],
) -> None:
    """What the body cannot carry fails naming its key: a segment FMU of the user's own, the
    features ArmBody lacks, and shared parameters that differ between segments. `given` is
    each segment's given parameters with their keys, `segments` and `cylinders` every
    parameter resolved."""
    from hil.scenario import fail

    file = scenario.source
    if scenario.robot.segment_fmu != "FeaSegment":
        raise fail(
            file,
            "robot.segment_fmu",
            'a segment FMU of your own needs robot.model = "segments" (the body is ArmBody)',
        )
    for own in given:
        if "substep" in own:
            raise fail(
                file,
                own["substep"][1],
                'the body (robot.model = "body") takes the substep its stability limit allows',
            )
    for name, modelled, why in REFUSED:
        for n, segment in enumerate(segments):
            if segment[name] != modelled:
                key = given[n][name][1] if name in given[n] else f"robot.segment.{name}"
                raise fail(
                    file,
                    key,
                    f'{segment[name]:g} is not modelled by robot.model = "body" ({why}): '
                    f'use robot.model = "segments"',
                )
    for name in SHARED_SEGMENT:
        _alike(file, "segment", name, [s[name] for s in segments], given)
    for name in SHARED_CYLINDER:
        _alike(file, "cylinder", name, [c[name] for c in cylinders], None)


def _alike(
    file: str,
    table: str,
    name: str,
    values: Sequence[float],
    given: Sequence[Mapping[str, tuple[float, str]]] | None,
) -> None:
    from hil.scenario import fail

    for n, value in enumerate(values):
        if value != values[0]:
            key = f"robot.{table}.{name}"
            if given is not None and name in given[n]:
                key = given[n][name][1]
            raise fail(
                file,
                key,
                f"differs between segments ({values[0]:g} for segment 1, {value:g} for "
                f"segment {n + 1}): the body's gas circuit and bend limit are shared; use "
                f'robot.model = "segments"',
            )


def values(
    segments: Sequence[Mapping[str, float]], cylinders: Sequence[Mapping[str, float]]
) -> dict[str, float]:
    """ArmBody's parameters for the arm whose segments (FeaSegment parameters, every one
    resolved) and cylinders (DriveCylinder's) are given; `check` has held."""
    out: dict[str, float] = {
        "n_segments": float(len(segments)),
        "planar": 1.0,
        "g_x": 0.0,
        "g_y": GRAVITY,
        "g_z": 0.0,
        "substep": 0.0,
    }
    for name in SHARED_SEGMENT:
        out[name] = segments[0][name]
    for name, target in SHARED_CYLINDER.items():
        out[target] = cylinders[0][name]
    for i, segment in enumerate(segments, start=1):
        for name, family in PER_SEGMENT.items():
            out[f"{family}_{i}"] = segment.get(name, 0.0)
        out[f"L_p_{i}"] = 0.0
        out[f"m_end_{i}"] = 0.0
    return out


def mass_matrix(lengths: Sequence[float], masses: Sequence[float]) -> list[list[float]]:
    """The straight arm's mass matrix [kg m^2] (each segment's mass uniform along its arc, as
    the body has it with L_p = m_end = 0): M_ij = sum over the arm's mass of the sideways
    displacements per bend angle, dp/dtheta_i . dp/dtheta_j (`bend_inertias` says what they
    are), by 3-point Gauss-Legendre over each arc (exact: the integrands are polynomials of
    degree 4 at most)."""
    nodes = (0.5 - math.sqrt(15.0) / 10.0, 0.5, 0.5 + math.sqrt(15.0) / 10.0)
    weights = (5.0 / 18.0, 8.0 / 18.0, 5.0 / 18.0)
    starts = [sum(lengths[:i]) for i in range(len(lengths))]
    n = len(lengths)
    M = [[0.0] * n for _ in range(n)]
    for k, (length, mass) in enumerate(zip(lengths, masses, strict=True)):
        for xi, w in zip(nodes, weights, strict=True):
            r = starts[k] + xi * length  # the point's distance from the base along the arm
            levers = [
                (r - starts[i] - lengths[i] / 2.0) if i < k else (xi * length) ** 2 / (2 * length)
                for i in range(k + 1)
            ]
            for i in range(k + 1):
                for j in range(k + 1):
                    M[i][j] += mass * w * levers[i] * levers[j]
    return M


def bend_inertias(lengths: Sequence[float], masses: Sequence[float]) -> list[float]:
    """The diagonal of the straight arm's mass matrix [kg m^2]: the inertia each bend carries,
    its own segment's and every outer one's (each segment's mass uniform along its arc, as the
    body has it with L_p = m_end = 0). Bending segment i by a small angle moves its own arc's
    point at s sideways by s^2 / (2 L_i) (m_i L_i^2 / 20 in all) and turns everything beyond
    its end about the middle of its arc: a point r beyond segment i's start moves by r - L_i / 2,
    and a uniform segment j of mass m_j whose centre is c_j beyond that start adds
    m_j ((c_j - L_i / 2)^2 + L_j^2 / 12)."""
    inertias = []
    for i, (length, mass) in enumerate(zip(lengths, masses, strict=True)):
        total = mass * length**2 / 20.0
        start = length  # where segment j starts, from segment i's start
        for outer_length, outer_mass in zip(lengths[i + 1 :], masses[i + 1 :], strict=True):
            lever = start + outer_length / 2.0 - length / 2.0
            total += outer_mass * (lever**2 + outer_length**2 / 12.0)
            start += outer_length
        inertias.append(total)
    return inertias


def ports(n: int) -> dict[str, str]:
    """Segment n's ports on the body, by the FeaSegment port they stand for."""
    return {
        "x_piston": f"{NAME}.x_piston_x_{n}",
        "p_a": f"{NAME}.p_a_x_{n}",
        "p_b": f"{NAME}.p_b_x_{n}",
        "kappa": f"{NAME}.kappa_x_{n}",
        "theta": f"{NAME}.theta_x_{n}",
        "theta_dot": f"{NAME}.theta_dot_x_{n}",
        "tau_ext": f"{NAME}.tau_ext_x_{n}",
    }


def segment_ports(n: int) -> dict[str, str]:
    """Segment n's ports on its FeaSegment FMU `segment{n}` (robot.model = "segments")."""
    return {
        name: f"segment{n}.{name}"
        for name in ("x_piston", "p_a", "p_b", "kappa", "theta", "theta_dot", "tau_ext")
    }


def arm_ports(scenario: Scenario, n: int) -> dict[str, str]:
    """Segment n's ports in the scenario's model of the arm."""
    return ports(n) if present(scenario) else segment_ports(n)
