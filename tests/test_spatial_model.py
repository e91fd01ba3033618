"""The spatial arm's controller-side model (robots/spatial_arm/controller) against the plant it
models, the ArmBody FMU (stepped through fmpy), and against tests/arm_reference.py's independent
transform chain: kinematics, the gas law, gravity, static equilibria (rests the damped FMU
settles into), the pistons that hold a shape, bends from markers, inverse kinematics, shape
fitting and the reachable envelope."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

import numpy as np
import pytest

import fmus
from hil.fmu.build import BuiltFmu, build_fmu
from hil.fmu.slave import FmuSlave
from robots.spatial_arm.controller import gas, ik, kinematics, marker_ik, statics
from robots.spatial_arm.controller.envelope import Envelope, sample_envelope
from robots.spatial_arm.controller.equilibrium import static_equilibrium
from robots.spatial_arm.controller.model import ArmModel
from tests.arm_reference import ArmReference, ArmSpec

ROOT = Path(__file__).resolve().parents[1]
ARM = ArmModel()
PLANAR = ArmModel(planar=True)
STEP_COMPLEX = 1e-30


@pytest.fixture(scope="session")
def arm_body_fmu() -> BuiltFmu:
    return build_fmu("ArmBody")


def per_pair(model: ArmModel, family: str, values: np.ndarray) -> dict[str, float]:
    """FMU inputs or parameters `family`_x_i / _y_i from a vector over the coordinates."""
    out = {}
    for j, value in enumerate(values):
        i, axis = divmod(j, model.n_dof)
        out[f"{family.format('xy'[axis])}_{i + 1}"] = float(value)
    return out


def fmu_values(fmu: BuiltFmu, parameters: dict, names: list[str]) -> np.ndarray:
    """The FMU's outputs right after initialisation."""
    with FmuSlave(fmu, "arm", parameters) as slave:
        return np.array(slave.get_reals([slave.value_reference(n) for n in names]))


def settle(fmu: BuiltFmu, model: ArmModel, pistons: np.ndarray, substep: float) -> np.ndarray:
    """q after 8 s at constant pistons from straight, damping 10x the default (the rest does
    not depend on it; the default's 0.04 damping ratio would take a minute to 1e-6 rad)."""
    params = {**model.to_fmu_parameters(), **per_pair(model, "x_piston_{}", pistons)}
    params.update({f"d_{i + 1}": 10.0 * d for i, d in enumerate(model.d)})
    params["substep"] = substep
    names = [f"theta_{'xy'[j % model.n_dof]}_{j // model.n_dof + 1}" for j in range(model.n_q)]
    with FmuSlave(fmu, "arm", params) as slave:
        for k in range(16):
            slave.do_step(0.5 * k, 0.5)
        return np.array(slave.get_reals([slave.value_reference(n) for n in names]))


def random_bends(rng: np.random.Generator, count: int, model: ArmModel = ARM) -> np.ndarray:
    q = rng.uniform(-1.2, 1.2, (count, model.n_q))
    theta = np.repeat(model.bend_angles(q), model.n_dof, axis=-1)
    return q * np.minimum(1.0, 0.99 * model.theta_max / theta)


# ------------------------------------------------------------------ the model


def test_defaults_are_arm_bodys() -> None:
    spec = tomllib.loads((fmus.source_root() / "ArmBody" / "model.toml").read_text())
    start = {name: entry["start"] for name, entry in spec["parameters"].items()}
    n = start["n_segments"]
    assert ARM.n_segments == n == 4 and ARM.n_nodes == start["n_nodes"] and not ARM.planar
    for name in ("L", "L_p", "mass", "m_end", "k", "d", "G_a"):
        value = start[name]
        expected = tuple(value[:n]) if isinstance(value, list) else (value,) * n
        assert getattr(ARM, name) == expected, name
    for name in ("theta_max", "bore", "stroke", "V_dead", "V_ch0", "C_a", "vacuum_factor"):
        assert getattr(ARM, name) == start[name], name
    for name in ("p_collapse", "x_seal", "p_atm"):
        assert getattr(ARM, name) == start[name], name
    assert ARM.gravity == (start["g_x"], start["g_y"], start["g_z"]) == (-9.81, 0.0, 0.0)
    # segments 5-8 take model.toml's values too
    eight = ArmModel.from_fmu_parameters({"n_segments": 8})
    assert eight.k == tuple(spec["parameters"]["k"]["start"])


def test_parameters_and_json_round_trip() -> None:
    model = ArmModel.from_fmu_parameters(
        {"n_segments": 3, "L_2": 0.2, "g_z": -9.81, "planar": 1, "substep": 1e-4, "x_piston_x_1": 0}
    )
    assert model.L == (0.12, 0.2, 0.10) and model.gravity == (-9.81, 0.0, -9.81)
    assert model.planar and model.n_q == 3
    assert ArmModel.from_fmu_parameters(model.to_fmu_parameters()) == model
    assert ArmModel.from_json(model.to_json()) == model
    assert ArmModel.from_json(ARM.to_json()) == ARM


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: ArmModel.from_fmu_parameters({"L_9": 0.1}), "'L_9' is unknown"),
        (lambda: ArmModel.from_fmu_parameters({"gas": 0}), "gas = 0"),
        (lambda: ArmModel(L=(0.1, 0.1)), "ArmModel.L_p: 4 values for 2 segments"),
        (lambda: ArmModel(k=(0.8, -0.5, 0.3, 0.15)), "ArmModel.k[1]: -0.5"),
        (lambda: ArmModel(x_seal=0.2), "ArmModel.x_seal"),
        (lambda: ArmModel(G_a=(1e-4,) * 4), "ArmModel.G_a[0]: a gas volume can reach zero"),
        (lambda: ArmModel.from_json('{"L": [0.1], "colour": 1}'), "unknown key 'colour'"),
        (lambda: ArmModel.from_json("[1"), "ArmModel JSON"),
    ],
)
def test_bad_parameters_are_named(make, message: str) -> None:
    with pytest.raises(ValueError, match=None) as error:
        make()
    assert message in str(error.value)
    assert "\n" not in str(error.value)


# ------------------------------------------------------------------ kinematics


@pytest.mark.parametrize("model", [ARM, PLANAR], ids=["spatial", "planar"])
def test_kinematics_are_arm_bodys(arm_body_fmu, model: ArmModel) -> None:
    rng = np.random.default_rng(11)
    names = [f"tip_{c}_{i + 1}" for i in range(model.n_segments) for c in "xyz"]
    worst = 0.0
    for q in [*random_bends(rng, 6, model), np.zeros(model.n_q), np.full(model.n_q, 1e-7)]:
        params = {**model.to_fmu_parameters(), **per_pair(model, "theta_{}_start", q)}
        tips = fmu_values(arm_body_fmu, params, names).reshape(-1, 3)
        ours = kinematics.markers(model, q)
        assert np.all(ours[0] == 0.0)
        worst = max(worst, np.max(np.abs(ours[1:] - tips)))
    assert worst < 1e-12  # measured 6e-17 m


def test_kinematics_match_the_independent_transform_chain() -> None:
    # tests/arm_reference.py writes the transform with gamma and the chord (bent arms only)
    spec = ArmSpec(ARM.L, ARM.mass, ARM.m_end, ARM.L_p, ARM.k, ARM.d, ARM.G_a, n_nodes=4)
    reference = ArmReference(spec)
    q = random_bends(np.random.default_rng(12), 5)
    points = reference.positions(q).real.reshape(5, ARM.n_segments, 5, 3)
    assert np.max(np.abs(points[:, :, -1, :] - kinematics.markers(ARM, q)[:, 1:])) < 1e-15
    xi = ARM.nodes[0]
    where = kinematics.Stations(np.repeat(np.arange(4), 4), np.tile(xi, 4), np.zeros(16))
    nodes, _ = kinematics.points(ARM, q, where)
    assert np.max(np.abs(points[:, :, :4, :].reshape(5, 16, 3) - nodes)) < 1e-15


@pytest.mark.parametrize("scale", [1.0, 1e-4, 0.0], ids=["bent", "slight", "straight"])
def test_jacobians_are_the_complex_step_derivatives(scale: float) -> None:
    rng = np.random.default_rng(13)
    q = random_bends(rng, 4) * scale
    where = kinematics.stations(ARM, 5)
    p, J = kinematics.points(ARM, q, where, jacobian=True)
    m, Jm = kinematics.marker_jacobian(ARM, q)
    for k, e in enumerate(np.eye(ARM.n_q)):
        probe = q + 1j * STEP_COMPLEX * e
        assert (
            np.max(np.abs(J[..., k] - kinematics.points(ARM, probe, where)[0].imag / STEP_COMPLEX))
            < 1e-14
        )
        assert (
            np.max(np.abs(Jm[..., k] - kinematics.markers(ARM, probe).imag / STEP_COMPLEX)) < 1e-14
        )
    # straight: bending segment s swings the tip sideways by the arm's length beyond the middle
    # of its arc
    if scale == 0.0:
        tip_j = kinematics.tip_jacobian(ARM, np.zeros(8))[1]
        beyond = [0.395, 0.27, 0.155, 0.05]  # 0.46 m less 0.065, 0.19, 0.305, 0.41
        assert np.allclose(tip_j[0, 0::2], beyond, atol=1e-15)
        assert np.allclose(tip_j[1, 1::2], beyond, atol=1e-15) and np.all(tip_j[2] == 0.0)


def test_bend_functions_are_continuous_and_accurate() -> None:
    # the series (below W = 1) and the closed forms (above) meet, and both are accurate
    W = np.array([1.0 - 1e-12, 1.0, 0.5, 0.01, 2.0])
    a, da, b, db = kinematics.bend_functions(W)
    t = np.sqrt(W)
    assert np.max(np.abs(a - np.sin(t) / t)) < 2e-16
    assert np.max(np.abs(b - 2.0 * np.sin(t / 2) ** 2 / W)) < 2e-16
    assert abs(da[0] - da[1]) < 1e-12 and abs(db[0] - db[1]) < 1e-12
    # at zero: a = 1, b = 1/2, a' = -1/6, b' = -1/24
    zero = kinematics.bend_functions(np.zeros(1))
    assert [float(f[0]) for f in zero] == [1.0, -1.0 / 6.0, 0.5, -1.0 / 24.0]


# ------------------------------------------------------------------ bends from markers


def test_segment_bend_inverts_a_segment_exactly() -> None:
    rng = np.random.default_rng(14)
    uv = random_bends(rng, 200, ArmModel(L=(0.1,), **_one(ARM)))
    for scale in (1.0, 1e-3, 1e-9, 0.0):
        r, _, _, _ = kinematics.tip_point(np.array(0.1), np.array(0.005), *(scale * uv).T)
        model = ArmModel(L=(0.1,), **_one(ARM))
        back = marker_ik.segment_bend(model, 0, r)
        assert np.max(np.abs(back - scale * uv)) < 1e-12, scale  # measured 4e-15
    # a tip beyond reach gives the limit's bend, towards it
    far = marker_ik.segment_bend(model, 0, np.array([0.2, 0.0, 0.0]))
    assert np.isclose(np.hypot(*far), model.theta_max) and far[0] > 0 and far[1] == 0.0


def _one(model: ArmModel) -> dict:
    return {name: getattr(model, name)[:1] for name in ("L_p", "mass", "m_end", "k", "d", "G_a")}


@pytest.mark.parametrize("model", [ARM, PLANAR], ids=["spatial", "planar"])
def test_bends_from_markers_recover_the_bends(model: ArmModel) -> None:
    rng = np.random.default_rng(15)
    q = random_bends(rng, 300, model)
    assert (
        np.max(np.abs(marker_ik.bends_from_markers(model, kinematics.markers(model, q)) - q))
        < 1e-12
    )
    small = 1e-8 * rng.normal(size=(50, model.n_q))
    back = marker_ik.bends_from_markers(model, kinematics.markers(model, small))
    assert np.max(np.abs(back - small)) < 1e-15
    assert np.all(marker_ik.bends_from_markers(model, kinematics.markers(model, 0 * q[0])) == 0.0)


def test_noisy_markers_give_bounded_bends() -> None:
    rng = np.random.default_rng(16)
    q = rng.uniform(-0.8, 0.8, (1000, 8))
    seen = kinematics.markers(ARM, q) + rng.normal(0.0, 1e-3, (1000, 5, 3))
    walk = marker_ik.bends_from_markers(ARM, seen)
    rms = np.sqrt(np.mean((walk - q) ** 2, axis=0))
    # 1 mm of noise: 0.015 rad on the base segment growing along the arm (each segment's base
    # frame comes from the ones before it), 0.11 rad at the tip
    assert 0.01 < rms[0] < 0.02 and 0.09 < rms[-1] < 0.13 and np.all(np.diff(rms[::2]) > 0)
    fit = marker_ik.fit_markers(ARM, seen)
    fitted = np.sqrt(np.mean((fit - q) ** 2, axis=0))
    assert np.all(fitted < rms) and np.all(ARM.bend_angles(fit) <= ARM.theta_max + 1e-12)
    # the fit is the least-squares one: no smaller marker residual than at its bends
    residual = np.sum((kinematics.markers(ARM, fit) - seen) ** 2)
    assert residual < np.sum((kinematics.markers(ARM, walk) - seen) ** 2)
    # a segment on its limit, seen through noise, is fitted within the limit
    limit = q[:50].copy()
    limit[:, 6:] *= ARM.theta_max / ARM.bend_angles(limit)[:, 3:]
    noisy = kinematics.markers(ARM, limit) + rng.normal(0.0, 1e-3, (50, 5, 3))
    fitted = ARM.bend_angles(marker_ik.fit_markers(ARM, noisy))[:, 3]
    assert np.all(fitted <= ARM.theta_max + 1e-15) and np.sum(fitted > ARM.theta_max - 1e-9) > 10
    # a lost marker leaves its segment and those after it unknown
    seen[0, 3] = np.nan
    lost = marker_ik.bends_from_markers(ARM, seen[0])
    assert np.all(np.isfinite(lost[:4])) and np.all(np.isnan(lost[4:]))


# ------------------------------------------------------------------ the gas and gravity


# sealed off mid-stroke (the sides differ), a softer channel wall and a deeper collapse
SKEWED = ArmModel(x_seal=0.03, C_a=3e-10, vacuum_factor=0.3, p_collapse=4e4)


@pytest.mark.parametrize("model", [ARM, SKEWED], ids=["default", "skewed"])
def test_gas_pressures_and_energy_are_arm_bodys(arm_body_fmu, model: ArmModel) -> None:
    rng = np.random.default_rng(17)
    names = [f"p_{s}_{a}_{i + 1}" for i in range(4) for a in "xy" for s in "ab"] + ["E_gas"]
    for q, x in zip(random_bends(rng, 4), rng.uniform(0.0, 0.1, (4, 8)), strict=True):
        params = {**model.to_fmu_parameters(), **per_pair(model, "theta_{}_start", q)}
        values = fmu_values(arm_body_fmu, {**params, **per_pair(model, "x_piston_{}", x)}, names)
        pair = statics.gas_torque(model, q, x)
        assert np.min(pair.p_b) < -5e3 and np.max(pair.p_a) > 5e3  # both regimes
        # ArmBody's vacuum Newton stops within 1e-10 Pa of the root; ours runs on
        assert np.max(np.abs(values[:-1:2] - pair.p_a)) < 1e-8
        assert np.max(np.abs(values[1:-1:2] - pair.p_b)) < 1e-8
        G_a = np.repeat(model.G_a, 2)
        assert abs(values[-1] - np.sum(gas.energy(model, G_a, q, x))) < 1e-12
    # the torque is the energy's slope, its slopes the implicit derivatives
    # (off the sealed state, where G(g)'s slope jumps and central differences lose an order)
    theta, x, h = np.linspace(-1.5, 1.5, 8), np.linspace(0.0, 0.1, 8), 1e-6
    t = gas.torque(ARM, 1.2e-5, theta, x)
    slope = (gas.energy(ARM, 1.2e-5, theta + h, x) - gas.energy(ARM, 1.2e-5, theta - h, x)) / (
        2 * h
    )
    assert np.max(np.abs(slope + t.tau)) < 1e-8
    d_theta = (
        gas.torque(ARM, 1.2e-5, theta + h, x).tau - gas.torque(ARM, 1.2e-5, theta - h, x).tau
    ) / (2 * h)
    assert np.max(np.abs(d_theta - t.d_theta)) < 1e-7 * np.max(np.abs(t.d_theta))
    assert np.all(t.d_x > 0.0) and np.all(t.d_theta < 0.0)


def test_gravity_is_arm_bodys_and_its_force_the_energy_slope(arm_body_fmu) -> None:
    rng = np.random.default_rng(18)
    q = random_bends(rng, 3)
    E, G = statics.gravity(ARM, q)
    h = 1e-5
    for k in range(3):
        start = ARM.to_fmu_parameters()
        assert (
            abs(
                fmu_values(
                    arm_body_fmu, {**start, **per_pair(ARM, "theta_{}_start", q[k])}, ["E_gravity"]
                )[0]
                - E[k]
            )
            < 1e-15
        )
    # G against the FMU's E_gravity by central differences (error h^2 ~ 1e-10)
    slope = []
    for e in np.eye(8):
        ends = [
            fmu_values(
                arm_body_fmu, per_pair(ARM, "theta_{}_start", q[0] + s * h * e), ["E_gravity"]
            )[0]
            for s in (1.0, -1.0)
        ]
        slope.append((ends[0] - ends[1]) / (2 * h))
    assert np.max(np.abs(np.array(slope) - G[0])) < 1e-9  # measured 7e-11
    # and against the independent chain, complex-step, exact
    spec = ArmSpec(ARM.L, ARM.mass, ARM.m_end, ARM.L_p, ARM.k, ARM.d, ARM.G_a, n_nodes=4)
    reference = ArmReference(spec)
    J = reference.jacobians(q)
    assert np.max(np.abs(-np.einsum("p,bpin,i->bn", reference.masses, J, ARM.g) - G)) < 1e-14
    # the gravity stiffness is G's derivative, symmetric
    H = statics.gravity_stiffness(ARM, q[0])
    assert np.max(np.abs(H - H.T)) < 1e-15
    column = (
        statics.gravity(ARM, q[0] + h * np.eye(8)[3])[1]
        - statics.gravity(ARM, q[0] - h * np.eye(8)[3])[1]
    ) / (2 * h)
    assert np.max(np.abs(column - H[:, 3])) < 1e-9


def test_straight_horizontal_arm_needs_arm_bodys_holding_torque() -> None:
    # fmus/ArmBody/README.md: 0.6857 N m on theta_x_1; none across the bending plane
    G = statics.gravity(ARM, np.zeros(8))[1]
    assert abs(G[0] - 0.685719) < 1e-6 and np.all(G[1::2] == 0.0)
    assert np.all(np.diff(G[0::2]) < 0.0)


# ------------------------------------------------------------------ equilibria


def test_equilibria_are_the_rests_arm_body_settles_into(arm_body_fmu) -> None:
    rng = np.random.default_rng(19)
    pistons = rng.uniform(0.0, 0.1, (3, 8))
    rest = static_equilibrium(ARM, pistons)
    assert np.all(rest.ok) and not np.any(rest.on_limit) and np.max(rest.residual) < 1e-14
    assert np.min(np.abs(rest.q)) > 1e-3  # every coordinate really bent
    for k in range(3):
        assert np.max(np.abs(settle(arm_body_fmu, ARM, pistons[k], 5e-4) - rest.q[k])) < 1e-9


def test_an_equilibrium_resting_on_the_bend_limit(arm_body_fmu) -> None:
    # the tip pairs at opposite ends push segment 4 onto its limit; the FMU rests there (its
    # resting segment creeps inwards by a few 1e-9 rad/s, hence 1e-6)
    pistons = np.array([0.08, 0.05, 0.05, 0.05, 0.05, 0.05, 0.1, 0.1])
    rest = static_equilibrium(ARM, pistons)
    assert rest.ok and list(rest.on_limit) == [False, False, False, True]
    assert abs(ARM.bend_angles(rest.q)[3] - ARM.theta_max) < 1e-15
    assert abs(rest.reaction[3] - 0.04055) < 1e-5  # [N m] the limit holds it
    assert rest.residual < 1e-13
    # Newton in the reduced coordinates (gamma on the limit) converges quadratically: 8 steps
    assert rest.iterations <= 10
    assert np.max(np.abs(settle(arm_body_fmu, ARM, pistons, 2.5e-4) - rest.q)) < 1e-6


def test_planar_equilibrium_is_arm_bodys(arm_body_fmu) -> None:
    pistons = np.array([0.1, 0.02, 0.07, 0.04])
    rest = static_equilibrium(PLANAR, pistons)
    assert rest.ok and np.max(np.abs(settle(arm_body_fmu, PLANAR, pistons, 5e-4) - rest.q)) < 1e-9


def test_arm_bodys_calibration_rests() -> None:
    # fmus/ArmBody/README.md: passive droop 29 deg down; full stroke on the base pair lifts the
    # base segment 12.6 deg above horizontal while segment 2 droops at -27 deg
    passive = static_equilibrium(ARM, np.full(8, 0.05))
    assert abs(np.degrees(passive.q[0]) + 29.41) < 0.01 and np.all(np.abs(passive.q[1::2]) < 1e-15)
    assert abs(kinematics.tip(ARM, passive.q)[0] + 0.2794) < 1e-4
    lift = np.full(8, 0.05)
    lift[0] = 0.1
    lifted = static_equilibrium(ARM, lift).q
    assert abs(np.degrees(lifted[0]) - 12.64) < 0.01 and abs(np.degrees(lifted[2]) + 26.71) < 0.01


def test_pistons_for_inverts_the_equilibrium() -> None:
    rng = np.random.default_rng(20)
    pistons = rng.uniform(0.0, 0.1, (200, 8))
    rest = static_equilibrium(ARM, pistons)
    free = ~np.any(rest.on_limit, axis=-1)
    assert 150 < np.sum(free) < 200  # some rest on the limit, whose pistons push beyond
    assert np.all(ARM.bend_angles(rest.q) <= ARM.theta_max + 1e-15)
    held = statics.pistons_for(ARM, rest.q[free])
    assert np.all(held.inside) and np.max(np.abs(held.x - pistons[free])) < 1e-12
    # bending the base up by a radian needs more than a full stroke: NaN, outside
    q = np.zeros(8)
    q[0] = 1.0
    beyond = statics.pistons_for(ARM, q)
    assert np.isnan(beyond.x[0]) and not beyond.inside[0] and beyond.tau[0] > beyond.tau_max[0]
    assert np.all(beyond.inside[1:]) and np.all((beyond.x[1:] >= 0) & (beyond.x[1:] <= 0.1))


# ------------------------------------------------------------------ inverse kinematics


def test_ik_reaches_a_reachable_goal_on_a_held_rest() -> None:
    rng = np.random.default_rng(21)
    rests = static_equilibrium(ARM, rng.uniform(0.01, 0.09, (2, 8))).q
    for known in rests:
        goal = kinematics.tip(ARM, known)
        result = ik.solve_ik(ARM, goal, margin=0.002)
        assert result.success and result.stable and result.error < 1e-9
        assert np.all((result.pistons >= 0.002 - 1e-12) & (result.pistons <= 0.098 + 1e-12))
        # the pistons hold it: the arm at rest there has its tip on the goal
        rest = static_equilibrium(ARM, result.pistons, q0=result.q)
        assert np.linalg.norm(kinematics.tip(ARM, rest.q) - goal) < 1e-6
        assert np.max(np.abs(rest.q - result.q)) < 1e-6
        # preferring straight bends less than the rest the goal came from; preferring that
        # rest returns it
        assert np.linalg.norm(result.q) < np.linalg.norm(known) - 0.05
        near = ik.solve_ik(ARM, goal, prefer=known)
        assert near.success and np.max(np.abs(near.q - known)) < 1e-6


def test_ik_reaches_a_rest_on_the_bend_limit() -> None:
    # the tip segment curled onto its limit (as in the equilibrium test): a reachable goal whose
    # preferred bends use the whole bend range
    pistons = np.array([0.08, 0.05, 0.05, 0.05, 0.05, 0.05, 0.1, 0.1])
    known = static_equilibrium(ARM, pistons).q
    result = ik.solve_ik(ARM, kinematics.tip(ARM, known), prefer=known, start=known)
    assert result.success and np.max(np.abs(result.q - known)) < 1e-6
    assert abs(ARM.bend_angles(result.q)[3] - ARM.theta_max) < 1e-9
    # held without the limit's help: the tip pairs pull less than the ends of their stroke
    assert np.all(result.pistons[6:] < 0.098)


def test_ik_refuses_unreachable_goals() -> None:
    beyond = ik.solve_ik(ARM, np.array([0.5, 0.0, 0.0]))  # the arm is 0.46 m long
    assert not beyond.success and beyond.error > 0.2
    # near the base, inside the convex hull of reachable tips but no rest puts the tip there
    dent = ik.solve_ik(ARM, np.array([0.1, 0.0, 0.1]))
    assert not dent.success and dent.error > 0.05
    # the result is still the best reachable approach: within the constraints
    assert np.all(np.isfinite(dent.pistons)) and dent.stable


def test_fit_shape_recovers_a_rest_from_its_backbone() -> None:
    q = static_equilibrium(ARM, np.array([0.07, 0.04, 0.03, 0.06, 0.05, 0.02, 0.06, 0.05])).q
    fit = ik.fit_shape(ARM, kinematics.backbone(ARM, q, 400))
    assert fit.success and fit.stable and fit.rms < 1e-6 and np.max(np.abs(fit.q - q)) < 1e-4
    # a curve the arm cannot follow: a circle bending up by 0.4 m radius, fitted as well as the
    # pistons allow (the base pair cannot hold the arm's own weight so bent)
    s = np.linspace(0.0, ARM.length, 200)
    circle = np.stack([0.4 * (1 - np.cos(s / 0.4)), 0 * s, 0.4 * np.sin(s / 0.4)], axis=-1)
    bent = ik.fit_shape(ARM, circle)
    assert bent.success and 1e-3 < bent.rms < 1e-2
    assert (
        np.min(np.minimum(bent.pistons - 0.002, 0.098 - bent.pistons)) < 1e-9
    )  # a pair at its end


# ------------------------------------------------------------------ the envelope


@pytest.fixture(scope="module")
def envelope() -> Envelope:
    return sample_envelope(ARM, 600, seed=3)


def test_envelope_is_seeded_and_holds_its_rests(envelope: Envelope) -> None:
    again = sample_envelope(ARM, 50, seed=3)
    assert np.array_equal(again.points, envelope.points[: len(again.points)])
    assert len(envelope.points) == 600 and envelope.q is not None and envelope.pistons is not None
    assert np.max(np.abs(kinematics.tip(ARM, envelope.q) - envelope.points)) == 0.0
    assert np.all(envelope.contains(envelope.points))
    # beyond the arm's length; near the base (inside the hull, nowhere near a rest)
    assert not envelope.contains(np.array([0.5, 0.0, 0.0]))
    assert envelope.hull_depth(np.array([0.1, 0.0, 0.1])) > 0.05
    assert not envelope.contains(np.array([0.1, 0.0, 0.1]))
    # the base lifted, the outer segments curled down: a rest well within (9 cm from the hull)
    pistons = np.array([0.1, 0.05, 0.02, 0.05, 0.02, 0.05, 0.02, 0.05])
    curled = kinematics.tip(ARM, static_equilibrium(ARM, pistons).q)
    assert envelope.contains(curled, margin=0.05)
    assert 0.03 < envelope.radius < 0.2


def test_drawn_goals_are_inside_and_reachable(envelope: Envelope) -> None:
    goals = envelope.draw_goals(np.random.default_rng(4), 12, margin=0.02)
    again = envelope.draw_goals(np.random.default_rng(4), 12, margin=0.02)
    assert np.array_equal(goals, again) and goals.shape == (12, 3)
    assert np.all(envelope.contains(goals, margin=0.02))
    for goal in goals[:2]:
        result = ik.solve_ik(ARM, goal, start=envelope.start_for(goal))
        assert result.success and result.error < 1e-9


def test_envelope_files_round_trip(envelope: Envelope, tmp_path: Path) -> None:
    envelope.save(tmp_path / "env.npz")
    loaded = Envelope.load(tmp_path / "env.npz")
    assert np.array_equal(loaded.points, envelope.points) and loaded.radius == envelope.radius
    assert np.array_equal(loaded.q, envelope.q) and np.array_equal(loaded.pistons, envelope.pistons)
    envelope.save(tmp_path / "env.csv")
    assert (tmp_path / "env.csv").read_text().splitlines()[0] == "x,y,z"
    tips = Envelope.load(tmp_path / "env.csv")
    assert np.array_equal(tips.points, envelope.points) and tips.radius == envelope.radius
    with pytest.raises(ValueError, match="saved as .npz or .csv"):
        envelope.save(tmp_path / "env.txt")


# ------------------------------------------------------------------ layering


def test_controller_side_imports_only_numpy_scipy_and_the_controller_side() -> None:
    """The controller side (the plant side's imports: tests/test_import_graph.py)."""
    allowed = ("numpy", "scipy", "filterpy", "controllers", "rigbus")
    allowed += ("robots.spatial_arm.controller",)
    allowed += ("__future__", "json", "math", "dataclasses", "functools", "typing", "pathlib")
    allowed += ("collections", "logging", "types")
    for path in (ROOT / "robots" / "spatial_arm" / "controller").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            for name in names:
                assert name.startswith(allowed), f"{path.name} imports {name}"
