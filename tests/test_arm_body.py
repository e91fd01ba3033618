"""ArmBody (fmus/ArmBody): the multibody PCC arm against energy, an independent formulation, the
single-segment model, hand counts and the gravity calibration (fmus/ArmBody/README.md)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping

import numpy as np
import pytest
from fmpy.validation import validate_fmu

import fmus
from hil.cosim import Algorithm, Connection, FmuParticipant
from hil.errors import FmuError
from hil.fmu.build import BuiltFmu, build_fmu
from hil.fmu.slave import FmuSlave
from hil.fmu.spec import generate_model_description, guid, load_spec
from tests import arm_body_ref
from tests.arm_reference import ArmReference, ArmSpec

G = 9.81
ENERGIES = [
    "E_kinetic",
    "E_gravity",
    "E_elastic",
    "E_gas",
    "E_dissipated",
    "W_actuation",
    "W_ext",
    "W_piston",
]
# the FeaSegment defaults (the planar arm's segment) in ArmBody's names
FEA = {"L": 0.06, "mass": 0.03, "k": 0.025, "d": 6e-3, "G_a": 7.7e-7}
FEA_GAS = {
    "bore": 0.0254,
    "stroke": 0.05,
    "V_dead": 5e-6,
    "V_ch0": 8e-6,
    "C_a": 1e-10,
    "vacuum_factor": 0.5,
    "p_collapse": 1e4,
    "x_seal": 0.025,
}
# the default spatial arm
SPATIAL = {
    "L": (0.12, 0.11, 0.10, 0.09),
    "mass": (0.16, 0.12, 0.09, 0.06),
    "m_end": 0.01,
    "L_p": 0.005,
}


@pytest.fixture(scope="session")
def arm_body_fmu() -> BuiltFmu:
    return build_fmu("ArmBody")


def per_segment(n: int, **families: float | tuple[float, ...]) -> dict[str, float]:
    """FMU parameters NAME_1 ... NAME_n from a value or a tuple per family."""
    out = {}
    for name, value in families.items():
        for i in range(n):
            out[f"{name}_{i + 1}"] = value[i] if isinstance(value, tuple) else value
    return out


def run(
    fmu: BuiltFmu,
    parameters: Mapping[str, float],
    duration: float,
    outputs: list[str],
    inputs: Callable[[float], Mapping[str, float]] | None = None,
    every: int = 1,
) -> dict[str, np.ndarray]:
    """Step the FMU at 1 ms with inputs(t) before each step; outputs at t = 0 and every `every`
    steps."""
    record: dict[str, list[float]] = {name: [] for name in ["time", *outputs]}
    with FmuSlave(fmu, "arm", parameters) as slave:
        vrs = [slave.value_reference(name) for name in outputs]

        def sample(t: float) -> None:
            record["time"].append(t)
            for name, value in zip(outputs, slave.get_reals(vrs), strict=True):
                record[name].append(value)

        sample(0.0)
        for k in range(int(round(duration / 1e-3))):
            if inputs is not None:
                for name, value in inputs(k * 1e-3).items():
                    slave.set(name, value)
            slave.do_step(k * 1e-3, 1e-3)
            if (k + 1) % every == 0:
                sample((k + 1) * 1e-3)
    return {name: np.asarray(values) for name, values in record.items()}


def stored(r: dict[str, np.ndarray]) -> np.ndarray:
    return r["E_kinetic"] + r["E_gravity"] + r["E_elastic"]


# ------------------------------------------------------------------ 1, 2: energy


BENT = {"theta_x_start": (0.25, -0.2, 0.15, 0.3), "theta_y_start": (0.15, 0.22, -0.25, 0.1)}


@pytest.mark.parametrize("gas", [1, 0])
def test_passive_arm_swinging_under_gravity_conserves_energy(arm_body_fmu, gas) -> None:
    # N = 4 spatial, undamped, from a bent non-planar shape at rest, pistons at rest: the gas is
    # a conservative spring (its stored energy in the balance) or absent
    params = {
        "gas": gas,
        "substep": 1e-4,
        **per_segment(4, d=0.0, **BENT),
    }
    r = run(arm_body_fmu, params, 10.0, ENERGIES + ["theta_1", "theta_4"], every=10)
    total = stored(r) + r["E_gas"]
    scale = r["E_kinetic"].max()
    drift = np.max(np.abs(total - total[0])) / scale
    # it really swung (0.4 J through the kinetic energy, the tip segment through more than a
    # radian) and never reached its limit
    assert scale > 0.4 and np.ptp(r["theta_4"]) > 1.0
    assert r["E_dissipated"][-1] == 0.0 and r["W_piston"][-1] == 0.0
    assert drift < 1e-6, drift
    # the gas's work on the arm is what its stored energy lost
    assert np.max(np.abs(r["W_actuation"] + r["E_gas"] - r["E_gas"][0])) / scale < 1e-6
    if gas:
        assert np.ptp(r["E_gas"]) > 0.01
    else:
        assert np.all(r["E_gas"] == 0.0)


def test_damped_driven_arm_balances_energy(arm_body_fmu) -> None:
    # default damping, every piston moving, external torques: both balances close
    def inputs(t: float) -> dict[str, float]:
        out = {}
        for i in range(1, 5):
            out[f"x_piston_x_{i}"] = 0.05 + 0.03 * math.sin(2 * math.pi * 0.7 * t + i)
            out[f"x_piston_y_{i}"] = 0.05 + 0.02 * math.sin(2 * math.pi * 1.1 * t - i)
            out[f"tau_ext_x_{i}"] = 0.02 * math.cos(3.0 * t + i)
            out[f"tau_ext_y_{i}"] = -0.015 * math.sin(2.0 * t)
        return out

    params = {"substep": 1e-4, **per_segment(4, **BENT)}
    r = run(arm_body_fmu, params, 5.0, ENERGIES, inputs, every=10)
    mechanical = stored(r) - stored(r)[0] + r["E_dissipated"] - r["W_actuation"] - r["W_ext"]
    total = (
        stored(r)
        + r["E_gas"]
        - stored(r)[0]
        - r["E_gas"][0]
        + r["E_dissipated"]
        - r["W_piston"]
        - r["W_ext"]
    )
    scale = max(r["E_dissipated"][-1], np.max(np.abs(r["W_actuation"])))
    # work really flowed every way
    assert r["E_dissipated"][-1] > 0.1 and np.ptp(r["W_piston"]) > 0.05
    assert np.ptp(r["W_ext"]) > 1e-3
    assert np.max(np.abs(mechanical)) / scale < 1e-6
    assert np.max(np.abs(total)) / scale < 1e-6


def test_planar_arm_is_the_spatial_arm_held_in_its_plane(arm_body_fmu) -> None:
    # the planar path (its own reduced arithmetic) against the spatial one, which the
    # independent formulation checks: gravity in the x-z plane, y pairs at rest, x pairs and
    # external torques driving, every x-z quantity and energy the same to rounding
    def inputs(t: float) -> dict[str, float]:
        out = {}
        for i in range(1, 5):
            out[f"x_piston_x_{i}"] = 0.05 + 0.03 * math.sin(2 * math.pi * 0.8 * t + i)
            out[f"tau_ext_x_{i}"] = 0.01 * math.cos(4.0 * t - i)
        return out

    params = {
        "g_x": -6.0,
        "g_z": -7.76,
        "substep": 2.5e-4,
        **per_segment(4, theta_x_start=(0.4, -0.3, 0.5, 0.2)),
    }
    names = [f"{v}_{i}" for v in ("theta_x", "theta_dot_x", "tip_x", "tip_z") for i in range(1, 5)]
    names += ENERGIES + ["M_11"]
    planar = run(arm_body_fmu, {**params, "planar": 1}, 1.0, names, inputs, every=10)
    spatial = run(arm_body_fmu, params, 1.0, names + ["theta_y_1", "tip_y_4"], inputs, every=10)
    assert np.all(spatial["theta_y_1"] == 0.0) and np.all(spatial["tip_y_4"] == 0.0)
    assert np.ptp(planar["theta_x_4"]) > 0.3
    for name in names:
        scale = max(np.max(np.abs(spatial[name])), 1e-3)
        assert np.max(np.abs(planar[name] - spatial[name])) < 1e-10 * scale, name


# ------------------------------------------------------------------ 3: independent formulation


Q0 = np.array([0.3, 0.2, -0.4, 0.25, 0.2, -0.5])
# gravity in 3-D: neither along the arm nor across it
GRAVITY = tuple(G * np.array([-7.0, 4.0, -5.0]) / np.linalg.norm([-7.0, 4.0, -5.0]))


@pytest.mark.parametrize("n", [1, 2, 3])
def test_free_response_agrees_with_an_independent_formulation(arm_body_fmu, n) -> None:
    spec = ArmSpec(
        L=(0.12, 0.11, 0.10)[:n],
        mass=(0.16, 0.12, 0.09)[:n],
        m_end=(0.01, 0.02, 0.015)[:n],
        L_p=(0.005, 0.008, 0.004)[:n],
        k=(0.8, 0.5, 0.3)[:n],
        d=(0.004, 0.0, 0.002)[:n],
        G_a=(1.2e-5, 8e-6, 5e-6)[:n],
        g=GRAVITY,
    )
    q0 = Q0[: 2 * n]
    duration = 0.5
    times = np.arange(int(round(duration / 1e-3)) + 1) * 1e-3
    q_ref, qd_ref = ArmReference(spec).simulate(q0, times)
    names = [f"theta_{axis}_{i + 1}" for i in range(n) for axis in "xy"]
    rates = [f"theta_dot_{axis}_{i + 1}" for i in range(n) for axis in "xy"]
    r = run(arm_body_fmu, {**spec.fmu(q0), "substep": 1e-4}, duration, names + rates)
    q = np.column_stack([r[name] for name in names])
    qd = np.column_stack([r[name] for name in rates])
    # the arm swung through a large motion
    assert np.max(np.ptp(q_ref, axis=0)) > 0.3
    assert np.max(np.abs(q - q_ref)) / np.max(np.abs(q_ref)) < 1e-6
    assert np.max(np.abs(qd - qd_ref)) / np.max(np.abs(qd_ref)) < 1e-6


def test_reference_conserves_energy() -> None:
    # the oracle itself: undamped, its energy is constant to its tolerance
    spec = ArmSpec(
        L=(0.12, 0.11),
        mass=(0.16, 0.12),
        m_end=(0.01, 0.02),
        L_p=(0.005, 0.008),
        k=(0.8, 0.5),
        d=(0.0, 0.0),
        G_a=(1.2e-5, 8e-6),
        g=GRAVITY,
    )
    reference = ArmReference(spec)
    times = np.linspace(0.0, 0.2, 5)
    q, qd = reference.simulate(Q0[:4], times)
    energy = [reference.energy(q[k], qd[k]) for k in range(len(times))]
    swing = 0.5 * qd[-1] @ reference.mass_matrix(q[-1][None])[0] @ qd[-1]
    assert swing > 0.01
    assert np.ptp(energy) < 1e-8 * swing


# ------------------------------------------------------------------ 4, 5: the single segment


def consistent_inertia(L: float, m: float, m_end: float, L_p: float) -> float:
    """A PCC segment's bend inertia about its base at small angles [kg m^2]: the arc's point at s
    moves by theta s^2 / (2 L), so int_0^L (m / L) (s^2 / (2 L))^2 ds = m L^2 / 20; the endplate
    beyond the distal end piece moves by theta (L / 2 + L_p): m_end (L / 2 + L_p)^2."""
    return m * L**2 / 20 + m_end * (L / 2 + L_p) ** 2


@pytest.mark.parametrize("m_end, L_p", [(0.0, 0.0), (0.02, 0.01)])
def test_one_segment_small_motion_matches_fea_segment(
    arm_body_fmu, fea_segment_fmu, m_end, L_p
) -> None:
    # a tenth of the planar arm's damping: an oscillating step response, set by the inertia
    L, m, d = FEA["L"], FEA["mass"], FEA["d"] / 10
    inertia = consistent_inertia(L, m, m_end, L_p)
    step = lambda t: 0.0252  # noqa: E731 - a 0.2 mm piston step at t = 0
    arm = run(
        arm_body_fmu,
        {
            "n_segments": 1,
            "planar": 1,
            "g_x": 0.0,
            "substep": 1e-4,
            "x_piston_x_1": 0.025,
            **FEA_GAS,
            **per_segment(1, **{**FEA, "d": d}, m_end=m_end, L_p=L_p),
        },
        0.3,
        ["theta_x_1", "p_a_x_1"],
        lambda t: {"x_piston_x_1": step(t)},
    )
    segment = run(
        fea_segment_fmu,
        {"mass": 20 * inertia / L**2, "d_bend": d, "substep": 1e-4},
        0.3,
        ["theta", "p_a"],
        lambda t: {"x_piston": step(t)},
    )
    peak = np.max(np.abs(segment["theta"]))
    assert 5e-3 < peak < 0.05  # small motion
    # equal to the small-motion model's accuracy (the bend's nonlinearity, ~theta^2)
    assert np.max(np.abs(arm["theta_x_1"] - segment["theta"])) < 5e-5 * peak
    assert np.max(np.abs(arm["p_a_x_1"] - segment["p_a"])) < 5e-5 * np.max(segment["p_a"])
    # and it is the inertia that agrees: a rigid rod's m L^2 / 3 would not
    rod = run(
        fea_segment_fmu,
        {
            "mass": 20 * (inertia + m * L**2 / 3 - m * L**2 / 20) / L**2,
            "d_bend": d,
            "substep": 1e-4,
        },
        0.3,
        ["theta"],
        lambda t: {"x_piston": step(t)},
    )
    assert np.max(np.abs(arm["theta_x_1"] - rod["theta"])) > 0.1 * peak


# per pair in order (x_1, y_1, x_2, ...): every spatial segment's bend stays inside its limit
PISTONS = (0.004, 0.028, 0.012, 0.038, 0.02, 0.046)


def fea_equilibrium(fmu: BuiltFmu, x_piston: float) -> float:
    """FeaSegment's static bend at a piston position (damped near critically, settled)."""
    r = run(fmu, {"d_bend": 8e-4, "x_piston": x_piston}, 5.0, ["theta", "theta_dot"], every=5000)
    assert abs(r["theta_dot"][-1]) < 1e-10
    return float(r["theta"][-1])


@pytest.mark.parametrize("planar", [1, 0])
def test_static_equilibria_without_gravity_equal_fea_segment(
    arm_body_fmu, fea_segment_fmu, planar
) -> None:
    # six planar segments, or three spatial ones with both pairs: with the same pistons and gas,
    # FeaSegment's bends are the arm's equilibrium to 1e-9 rad. Six planar segments settle
    # slowly (the base carries the outer arm: a 0.4 Hz first mode), so that arm starts at
    # FeaSegment's bends and must stay there (an equilibrium off by e oscillates about its own
    # by e); three spatial ones settle from straight within the run
    n = 6 if planar else 3
    pairs = [(i, axis) for i in range(n) for axis in "xy"[: 2 - planar]]
    names = [f"theta_{axis}_{i + 1}" for i, axis in pairs]
    expected = {name: fea_equilibrium(fea_segment_fmu, PISTONS[j]) for j, name in enumerate(names)}
    params = {
        "n_segments": n,
        "planar": planar,
        "g_x": 0.0,
        "substep": 2.5e-4,
        **FEA_GAS,
        **per_segment(n, **{**FEA, "d": (6e-3, 3e-3, 1.2e-3)[:n] if not planar else FEA["d"]}),
        **per_segment(n, m_end=0.0, L_p=0.0),
    }
    for j, (i, axis) in enumerate(pairs):
        params[f"x_piston_{axis}_{i + 1}"] = PISTONS[j]
        if planar:
            params[f"theta_x_start_{i + 1}"] = expected[names[j]]
    r = run(arm_body_fmu, params, 1.0 if planar else 5.0, names)
    assert max(abs(value) for value in expected.values()) > 1.0  # large bends
    for name in names:
        if planar:
            assert np.max(np.abs(r[name] - expected[name])) < 1e-9, name
        else:
            assert abs(r[name][-1] - expected[name]) < 1e-9, name
            assert np.ptp(r[name]) > 0.3  # it did settle there from straight


# ------------------------------------------------------------------ 6: the base carries the arm


def test_base_coordinate_carries_the_whole_outer_arm(arm_body_fmu) -> None:
    # planar, six segments of different lengths, masses, end pieces and endplates, straight. A
    # small bend theta_1 turns segment 1's chord about the middle of its arc, so a point beyond
    # it, a distance c from there along the straight arm, moves by theta_1 c: M_11 is segment
    # 1's own m L^2 / 20 plus the outer arm's moment of inertia about that point
    L = (0.06, 0.055, 0.05, 0.045, 0.04, 0.035)
    mass = (0.03, 0.028, 0.025, 0.02, 0.018, 0.015)
    m_end = (0.005, 0.004, 0.006, 0.003, 0.002, 0.008)
    L_p = (0.004, 0.003, 0.005, 0.002, 0.006, 0.001)
    params = {
        "n_segments": 6,
        "planar": 1,
        "substep": 1e-5,
        **per_segment(6, L=L, mass=mass, m_end=m_end, L_p=L_p),
    }
    with FmuSlave(arm_body_fmu, "arm", params) as slave:
        base_inertia = slave.get("M_11")
    pivot = L_p[0] + L[0] / 2  # along the straight arm from the base
    hand = mass[0] * L[0] ** 2 / 20 + m_end[0] * (L[0] / 2 + L_p[0]) ** 2
    start = L_p[0] + L[0] + L_p[0]  # segment 2's base
    for i in range(1, 6):
        a, b = start + L_p[i] - pivot, start + L_p[i] + L[i] - pivot  # its arc, about the pivot
        hand += mass[i] / L[i] * (b**3 - a**3) / 3  # (m / L) int_a^b c^2 dc
        start += 2 * L_p[i] + L[i]
        hand += m_end[i] * (start - pivot) ** 2
    assert base_inertia == pytest.approx(hand, rel=1e-12)
    # not the rigid arm's turning about the base (the bend is not a rigid turn): that is larger
    rigid, start = mass[0] * (L_p[0] ** 2 + L_p[0] * L[0] + L[0] ** 2 / 3), 0.0
    for i in range(6):
        start += L_p[i]
        if i > 0:
            rigid += mass[i] * ((start + L[i]) ** 3 - start**3) / (3 * L[i])
        start += L[i] + L_p[i]
        rigid += m_end[i] * start**2
    assert base_inertia < 0.75 * rigid


# ------------------------------------------------------------------ 7: validation and libcosim


def test_fmu_passes_fmpy_validation_and_declares_no_feedthrough(arm_body_fmu) -> None:
    assert validate_fmu(str(arm_body_fmu.path)) == []
    spec = load_spec(fmus.source_root() / "ArmBody")
    root = ET.fromstring(generate_model_description(spec, guid(spec, "digest")))
    assert all(u.get("dependencies") == "" for u in root.find("ModelStructure/Outputs"))
    index = {v.get("name"): i + 1 for i, v in enumerate(root.iter("ScalarVariable"))}
    initial = {
        int(u.get("index")): set(map(int, u.get("dependencies").split()))
        for u in root.find("ModelStructure/InitialUnknowns")
    }
    assert index["x_piston_x_3"] in initial[index["p_a_x_3"]]
    assert index["x_piston_y_3"] not in initial[index["p_a_x_3"]]
    assert index["x_piston_x_1"] not in initial[index["theta_x_1"]]
    texts = [v.get("description") for v in root.iter("ScalarVariable")]
    assert not any(".md" in text or "section" in text for text in texts)


LIBCOSIM_SCRIPT = """
import json, sys
from libcosimpy.CosimExecution import CosimExecution
from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
from libcosimpy.CosimObserver import CosimObserver
from libcosimpy.CosimSlave import CosimLocalSlave
log_output_level(CosimLogLevel.ERROR)
args = json.loads(sys.argv[1])
ex = CosimExecution.from_step_size(step_size=1_000_000)
cyl = ex.add_local_slave(CosimLocalSlave(fmu_path=args["cylinder"], instance_name="cylinder1"))
arm = ex.add_local_slave(CosimLocalSlave(fmu_path=args["arm"], instance_name="arm"))
vr = args["vr"]
ex.connect_real_variables(cyl, vr["x"], arm, vr["x_piston_x_1"])
ex.connect_real_variables(arm, vr["p_a_x_1"], cyl, vr["cyl_p_a"])
ex.connect_real_variables(arm, vr["p_b_x_1"], cyl, vr["cyl_p_b"])
ex.real_initial_value(cyl, vr["x_ref"], 0.080)
ex.real_initial_value(cyl, vr["x_start"], 0.05)
ex.real_initial_value(cyl, vr["bore"], 0.03175)
ex.real_initial_value(cyl, vr["stroke"], 0.1)
observer = CosimObserver.create_last_value()
ex.add_observer(observer)
rows = []
for k in range(1, args["samples"] + 1):
    ex.simulate_until(k * args["every"] * 1_000_000)
    rows.append(observer.last_real_values(cyl, [vr["x"]]) +
                observer.last_real_values(arm, [vr["theta_x_1"], vr["tip_x_4"], vr["p_a_x_1"]]))
print(json.dumps(rows))
"""


def test_libcosim_runs_the_arm_and_agrees_with_our_master(arm_body_fmu) -> None:
    # the default arm hanging off a horizontal base, its base x pair driven by a DriveCylinder
    # of the arm's bore and stroke: libcosim's fixed-step master and ours, at 1 ms
    cylinder = build_fmu("DriveCylinder")
    samples, every = 20, 50
    c, a = cylinder.spec.variable, arm_body_fmu.spec.variable
    names = ("x_piston_x_1", "p_a_x_1", "p_b_x_1", "theta_x_1", "tip_x_4")
    vr = {name: a(name).value_reference for name in names}
    for name in ("x", "x_ref", "x_start", "bore", "stroke"):
        vr[name] = c(name).value_reference
    vr["cyl_p_a"], vr["cyl_p_b"] = c("p_a").value_reference, c("p_b").value_reference
    args = {
        "cylinder": str(cylinder.path),
        "arm": str(arm_body_fmu.path),
        "vr": vr,
        "samples": samples,
        "every": every,
    }
    result = subprocess.run(
        ["taskset", "-c", "0", sys.executable, "-c", LIBCOSIM_SCRIPT, json.dumps(args)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    theirs = np.array(json.loads(result.stdout.strip().splitlines()[-1]))

    cylinder_parameters = {"x_ref": 0.080, "x_start": 0.05, "bore": 0.03175, "stroke": 0.1}
    participants = [
        FmuParticipant(FmuSlave(cylinder, "cylinder1", cylinder_parameters)),
        FmuParticipant(FmuSlave(arm_body_fmu, "arm")),
    ]
    master = Algorithm(
        participants,
        [
            Connection("cylinder1.x", "arm.x_piston_x_1"),
            Connection("arm.p_a_x_1", "cylinder1.p_a"),
            Connection("arm.p_b_x_1", "cylinder1.p_b"),
        ],
        1e-3,
    )
    ours = []
    for k in range(1, samples + 1):
        master.advance_to(k * every)
        ours.append([master.values[f] for f in ("cylinder1.x", "arm.theta_x_1", "arm.tip_x_4")])
        ours[-1].append(master.values["arm.p_a_x_1"])
    for p in participants:
        p.close()
    ours_array = np.array(ours)
    # the piston travelled, the arm drooped and the base pair pushed back
    assert ours_array[-1, 0] > 0.07 and ours_array[-1, 3] > 10e3
    assert np.ptp(ours_array[:, 1]) > 0.1
    scale = np.max(np.abs(ours_array), axis=0)
    assert np.max(np.abs(theirs - ours_array) / scale) < 1e-12


# ------------------------------------------------------------------ 8: gravity on the real arm


def holding_torques(
    L: tuple[float, ...], mass: tuple[float, ...], m_end: float, L_p: float, g: float = G
) -> np.ndarray:
    """The generalised torques that hold the straight arm horizontal against g (hand count).

    A small bend theta_j moves a point of segment j's arc at the fraction xi by theta_j L_j xi^2 / 2
    (mean L_j / 6 over the arc), its endplate by theta_j (L_j / 2 + L_p), and any point beyond by
    theta_j (L_j / 2 + L_p + z), z its distance along the arm from segment j's tip.
    """
    n = len(L)
    torque = np.zeros(n)
    for j in range(n):
        torque[j] = g * (mass[j] * L[j] / 6 + m_end * (L[j] / 2 + L_p))
        z = 0.0
        for o in range(j + 1, n):
            centre = z + L_p + L[o] / 2
            torque[j] += g * mass[o] * (L[j] / 2 + L_p + centre)
            z += 2 * L_p + L[o]
            torque[j] += g * m_end * (L[j] / 2 + L_p + z)
    return torque


def channel_torque(g: float, G_a: float, vacuum_factor: float, p_collapse: float) -> float:
    """H(g) of one channel [N m] (fmus/common/gas_circuit.h)."""
    if g >= 0.0:
        return G_a * g
    return G_a * (vacuum_factor * g + (1 - vacuum_factor) * p_collapse * math.expm1(g / p_collapse))


def settle(fmu: BuiltFmu, extra: Mapping[str, float], names: list[str]) -> dict[str, float]:
    """The default arm's static equilibrium: damping near critical for its modes (which does not
    move it) for 6 s."""
    params = {"substep": 1e-4, **per_segment(4, d=(0.3, 0.12, 0.04, 0.01)), **extra}
    r = run(fmu, params, 6.0, [*names, "E_kinetic"], every=6000)
    assert r["E_kinetic"][-1] < 1e-14
    return {name: float(r[name][-1]) for name in names}


# the calibrated figures (README.md): the arm's droop, the torque that holds it straight and
# horizontal on the base coordinate, and the base pair's full stroke
DROOP_MM = 279.4
HOLD_BASE = 0.6857  # N m
FULL_STROKE_BASE = 0.9099  # N m


def test_gravity_droops_the_arm_and_full_stroke_on_the_base_pair_lifts_it(arm_body_fmu) -> None:
    straight = settle(arm_body_fmu, {"g_x": 0.0}, ["tip_x_4", "tip_z_4"])
    assert straight == pytest.approx({"tip_x_4": 0.0, "tip_z_4": 0.46}, abs=1e-12)
    names = ["tip_x_4", "theta_x_1", "theta_x_2", "p_a_x_1", "theta_y_1"]
    passive = settle(arm_body_fmu, {}, names)
    droop_mm = -passive["tip_x_4"] * 1e3
    print(f"droop of the passive arm, base horizontal: tip {droop_mm:.1f} mm down")
    assert droop_mm == pytest.approx(DROOP_MM, abs=0.5)
    assert passive["theta_y_1"] == 0.0  # gravity in the x-z plane keeps it there

    hold = holding_torques(SPATIAL["L"], SPATIAL["mass"], 0.01, 0.005)
    print(f"holding torques on theta_x (base to tip) [N m]: {np.round(hold, 4)}")
    assert hold[0] == pytest.approx(HOLD_BASE, abs=1e-4)
    # the FMU agrees: those torques hold the straight arm still
    held = run(
        arm_body_fmu,
        {"substep": 2e-4, "gas": 0, **per_segment(4, tau_ext_x=tuple(hold))},
        0.2,
        ["theta_1", "theta_2", "theta_3", "theta_4"],
    )
    assert max(np.max(np.abs(held[f"theta_{i}"])) for i in range(1, 5)) < 1e-12

    with FmuSlave(arm_body_fmu, "arm", {"x_piston_x_1": 0.1}) as blocked:  # straight, at rest
        g_a, g_b = blocked.get("p_a_x_1"), blocked.get("p_b_x_1")
    full = channel_torque(g_a, 1.2e-5, 0.5, 3e4) - channel_torque(g_b, 1.2e-5, 0.5, 3e4)
    print(
        f"base pair at full stroke, arm straight: p_a {g_a / 1e3:.1f} kPa, p_b {g_b / 1e3:.1f} kPa,"
        f" torque {full:.4f} N m = {full / hold[0]:.2f} x the holding torque {hold[0]:.4f} N m"
    )
    assert full == pytest.approx(FULL_STROKE_BASE, abs=1e-4)
    # the statement: it lifts with margin, not with the whole stroke to spare
    assert 1.2 < full / hold[0] < 1.6
    # and within the thesis's 3-8 psi working band
    assert 3 * 6894.76 < g_a < 8 * 6894.76

    lifted = settle(arm_body_fmu, {"x_piston_x_1": 0.1}, names)
    print(
        f"full stroke on the base pair: base segment at {math.degrees(lifted['theta_x_1']):.1f}"
        f" deg above horizontal, p_a {lifted['p_a_x_1'] / 1e3:.1f} kPa"
    )
    # the base segment rises above horizontal, nowhere near curling past vertical, and the
    # pressure stays in the band while the bend reopens the channel
    assert 0.1 < lifted["theta_x_1"] < 0.5
    assert 35e3 < lifted["p_a_x_1"] < 55e3
    # and the rest of the arm, unactuated, still droops
    assert lifted["theta_x_2"] < -0.2 and lifted["tip_x_4"] > passive["tip_x_4"]


def test_the_default_arm_reproduces_its_reference_result(arm_body_fmu) -> None:
    # fmus/ArmBody/ArmBody_ref.csv, the default arm drooping from straight (regenerated only by
    # `python -m tests.arm_body_ref --regenerate`); to 1e-9 of each column's range, not bits: a
    # compiler may order the arithmetic differently
    want = arm_body_ref.read()
    got = arm_body_ref.simulate()
    assert got.shape == want.shape
    scale = np.max(np.abs(want), axis=0)
    assert np.all(np.abs(got - want) <= 1e-9 * scale)


# ------------------------------------------------------------------ errors and limits


def test_inconsistent_parameters_and_inputs_fail_with_one_clear_message(arm_body_fmu) -> None:
    with pytest.raises(FmuError, match="substep = 0.001: beyond the stability limit"):
        FmuSlave(arm_body_fmu, "arm", per_segment(4, d=0.5))
    with pytest.raises(FmuError, match="theta_y_start_2 = 0.1: a planar arm bends in x only"):
        FmuSlave(arm_body_fmu, "arm", {"planar": 1, "theta_y_start_2": 0.1})
    with pytest.raises(FmuError, match="a bend of 1.7 rad is beyond theta_max"):
        FmuSlave(arm_body_fmu, "arm", {"theta_x_start_3": 1.7})
    with pytest.raises(FmuError, match="a gas volume of segment 1 can reach zero"):
        FmuSlave(arm_body_fmu, "arm", {"V_ch0": 5e-6, "V_dead": 1e-6})
    with (
        FmuSlave(arm_body_fmu, "arm") as slave,
        pytest.raises(FmuError, match=r"x_piston_y_2 = 0.2 is outside the stroke \[0, 0.1\]"),
    ):
        slave.set("x_piston_y_2", 0.2)
        slave.do_step(0.0, 1e-3)


def test_the_substep_limit_is_the_fastest_mode_of_the_arm(arm_body_fmu) -> None:
    # six planar FeaSegment segments: the coupled arm's fastest mode is the damping of a tip
    # motion, lambda = -rho(M^-1 D) (from the independent mass matrix), and RK4 needs
    # h |lambda| <= 2.5: the FMU takes 2.5e-4 s and refuses 2.7e-4 s, naming that limit
    n = 6
    spec = ArmSpec(
        L=(FEA["L"],) * n,
        mass=(FEA["mass"],) * n,
        m_end=(0.0,) * n,
        L_p=(0.0,) * n,
        k=(FEA["k"],) * n,
        d=(FEA["d"],) * n,
        G_a=(FEA["G_a"],) * n,
    )
    M = ArmReference(spec).mass_matrix(np.full(2 * n, 1e-7)[None])[0][::2, ::2]
    fastest = np.max(np.linalg.eigvals(np.linalg.solve(M, FEA["d"] * np.eye(n))).real)
    assert fastest == pytest.approx(9650, rel=0.01)
    params = {
        "n_segments": n,
        "planar": 1,
        "g_x": 0.0,
        **FEA_GAS,
        **per_segment(n, **FEA, m_end=0.0, L_p=0.0, x_piston_x=0.025),
    }
    with FmuSlave(arm_body_fmu, "arm", {**params, "substep": 2.5e-4}) as slave:
        slave.do_step(0.0, 1e-3)
    with pytest.raises(FmuError, match="substep = 0.00027: beyond the stability limit") as error:
        FmuSlave(arm_body_fmu, "arm", {**params, "substep": 2.7e-4})
    limit = float(str(error.value).split("stability limit ")[1].split(" s")[0])
    assert limit == pytest.approx(2.5 / fastest, rel=0.01)


def test_eight_segments_run_and_the_limit_stops_segments(arm_body_fmu) -> None:
    # the largest arm (16 coordinates) with its base and tip pairs driven into their bend limit:
    # the segments stop there and rest on it while the tip whips along it; the energy the stops
    # take is dissipated and both balances hold
    params = {
        "n_segments": 8,
        "substep": 5e-5,
        "theta_max": 0.8,
        **per_segment(8, L=0.05, mass=0.03, k=0.15, G_a=3e-6),
    }
    ramp = lambda t: min(t / 0.2, 1.0)  # noqa: E731

    def inputs(t: float) -> dict[str, float]:
        return {"x_piston_x_8": 0.05 + 0.05 * ramp(t), "x_piston_y_8": 0.05 - 0.05 * ramp(t)}

    r = run(arm_body_fmu, params, 1.0, ENERGIES + ["theta_1", "theta_8"], inputs)
    at_limit = r["theta_8"] > 0.8 - 1e-9
    assert np.max(r["theta_8"]) <= 0.8 + 1e-15 and np.mean(at_limit) > 0.5
    assert np.max(r["theta_1"]) > 0.8 - 1e-9  # the base is thrown against its limit too
    total = stored(r) + r["E_gas"] + r["E_dissipated"] - r["W_piston"] - r["W_ext"]
    mechanical = stored(r) + r["E_dissipated"] - r["W_actuation"] - r["W_ext"]
    scale = r["W_piston"][-1]
    assert np.max(np.abs(total - total[0])) < 1e-6 * scale
    assert np.max(np.abs(mechanical - mechanical[0])) < 1e-6 * scale
    # the stops took energy beyond the damping's share
    assert r["E_dissipated"][-1] > 0.1
