"""Environment FMU (issue 12): contact geometry against controllers/kinematics.py, generalised
torques by virtual work, a passive arm coming to rest against a wall with the penetration its
stiffness sets, energy that contact never creates, objects pushed and stopped by table friction,
fmpy validation, and the indexed variable families of model.toml."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import pytest

import fmus
from controllers import kinematics
from hil.cli import main
from hil.errors import BuildError
from hil.fmu.build import BuiltFmu, build_fmu
from hil.fmu.slave import FmuSlave
from hil.fmu.spec import generate_header, load_spec

K_CONTACT = 1000.0
LENGTH = 0.06
H = 1e-3


@pytest.fixture(scope="module")
def environment_fmu() -> BuiltFmu:
    return build_fmu("Environment")


@pytest.fixture(scope="module")
def segment_fmu() -> BuiltFmu:
    return build_fmu("FeaSegment")


def with_wall(params: dict[str, float], wall: int, vertices: Sequence[tuple[float, float]]) -> None:
    params["n_walls"] = max(params.get("n_walls", 0), wall)
    params[f"wall{wall}_n"] = len(vertices)
    for i, (x, y) in enumerate(vertices, 1):
        params[f"wall{wall}_x_{i}"] = x
        params[f"wall{wall}_y_{i}"] = y


def backbone(kappas: Sequence[float], n_samples: int) -> list[tuple[int, np.ndarray]]:
    """(segment, point) of every backbone sample, from controllers.kinematics (the shared truth)."""
    points = []
    pose = (0.0, 0.0, 0.0)
    for j, kappa in enumerate(kappas):
        for k in range(1, n_samples + 1):
            points.append(
                (j, np.array(kinematics.segment_end(pose, kappa, LENGTH * k / n_samples)[:2]))
            )
        pose = kinematics.segment_end(pose, kappa, LENGTH)
    return points


def distance_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    t = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + t * (b - a))))


def static_outputs(fmu: BuiltFmu, params: Mapping[str, float], kappas: Sequence[float]) -> dict:
    """Outputs in initialisation mode at curvatures `kappas`, at rest."""
    inputs = {f"kappa_{i + 1}": k for i, k in enumerate(kappas)}
    with FmuSlave(fmu, "env", {**params, **inputs}) as env:
        n = len(kappas)
        return {
            "tau": np.array([env.get(f"tau_ext_{i + 1}") for i in range(n)]),
            "penetration": np.array([env.get(f"penetration_{i + 1}") for i in range(n)]),
            "force": np.array([env.get(f"contact_force_{i + 1}") for i in range(n)]),
            "E_contact": env.get("E_contact"),
        }


# ------------------------------------------------------------------ geometry, statics


def test_penetration_follows_the_pcc_backbone_of_kinematics_py(environment_fmu) -> None:
    rng = np.random.default_rng(12)
    kappas = rng.uniform(-8.0, 8.0, 4)
    a, b = np.array([0.05, 0.07]), np.array([0.25, -0.05])
    params = {"n_segments": 4, "n_samples": 5, "arm_mobility": 0.0}
    with_wall(params, 1, [tuple(a), tuple(b)])
    out = static_outputs(environment_fmu, params, kappas)
    expected = np.zeros(4)
    for j, p in backbone(kappas, 5):
        expected[j] = max(expected[j], 0.01 - distance_to_segment(p, a, b))
    assert expected.max() > 1e-3  # the wall really crosses the arm
    np.testing.assert_allclose(out["penetration"], expected, atol=1e-12)


@pytest.mark.parametrize("stub", [[(0.105, 0.05), (0.105, 0.02)], [(0.105, 0.02), (0.105, 0.05)]])
def test_a_wall_ending_short_of_the_arm_does_not_touch_it(environment_fmu, stub) -> None:
    # the stub's line passes through the straight arm, its end stays 10 mm clear of the capsule
    params = {"n_segments": 3, "arm_mobility": 0.0}
    with_wall(params, 1, stub)
    out = static_outputs(environment_fmu, params, [0.0, 0.0, 0.0])
    assert np.all(out["penetration"] == 0.0) and np.all(out["tau"] == 0.0)
    # and 1 mm lower, its end touches the capsule of the point under it by 1 mm
    with_wall(params, 1, [(x, y - 0.011) for x, y in stub])
    touching = static_outputs(environment_fmu, params, [0.0, 0.0, 0.0])["penetration"]
    assert touching == pytest.approx([0.0, 1e-3, 0.0], abs=1e-12)


@pytest.mark.parametrize("with_object", [False, True])
def test_torque_is_the_virtual_work_of_the_contact(environment_fmu, with_object) -> None:
    # conservative contact at rest: tau_i = -dE_contact/dtheta_i (work-conjugate to the bend)
    kappas = np.array([3.0, 5.0, -2.0])
    params: dict[str, float] = {"n_segments": 3, "arm_mobility": 0.0, "d_contact": 0.0}
    with_wall(params, 1, [(0.0, 0.05), (0.1, 0.03), (0.2, 0.02)])
    if with_object:
        params.update(n_objects=1, object_x0_1=0.17, object_y0_1=0.03, object_radius_1=0.02)
    out = static_outputs(environment_fmu, params, kappas)
    assert np.all(out["penetration"][1:] > 1e-4)
    delta = 1e-7  # rad
    for i in range(3):
        up, down = kappas.copy(), kappas.copy()
        up[i] += delta / LENGTH
        down[i] -= delta / LENGTH
        derivative = (
            static_outputs(environment_fmu, params, up)["E_contact"]
            - static_outputs(environment_fmu, params, down)["E_contact"]
        ) / (2 * delta)
        assert out["tau"][i] == pytest.approx(-derivative, rel=1e-5, abs=1e-10)


def test_a_wall_above_the_tip_pushes_every_segment_down(environment_fmu) -> None:
    params = {"n_segments": 3, "arm_mobility": 0.0}
    with_wall(params, 1, [(-0.1, 0.009), (0.3, 0.009)])
    out = static_outputs(environment_fmu, params, [0.0, 0.0, 0.0])
    # every point of the straight arm penetrates 1 mm and is pushed in -y by 1 N
    assert out["penetration"] == pytest.approx([1e-3] * 3, abs=1e-12)
    assert np.all(out["tau"] < 0.0)
    # PCC levers at zero bend (closed form): bending segment i lifts its own point at arc s by
    # s^2 / (2 L) per radian, moves its end by L / 2 and turns everything beyond about its end
    for i in range(3):
        lever = 0.0
        for j, p in backbone([0.0] * 3, 8):
            if j == i:
                s = p[0] - i * LENGTH
                lever += s * s / (2 * LENGTH)
            elif j > i:
                lever += LENGTH / 2 + p[0] - (i + 1) * LENGTH
        assert out["tau"][i] == pytest.approx(-K_CONTACT * 1e-3 * lever, rel=1e-9)
    assert out["force"][2] == pytest.approx(8 * K_CONTACT * 1e-3, rel=1e-9)


# ------------------------------------------------------------------- coupled with FeaSegment


def coupled_run(
    environment_fmu: BuiltFmu,
    segment_fmu: BuiltFmu,
    n: int,
    env_params: Mapping[str, float],
    drive: Sequence[float] | None,
    duration: float,
    release_at: float = math.inf,
) -> dict[str, np.ndarray]:
    """FeaSegments (pistons sealed at mid-stroke, so only gas stiffness and bending) and the
    Environment stepped as hil's master steps them (Jacobi: each reads the other's outputs of
    the previous tick); `drive` is a constant torque added to each segment's tau_ext until
    `release_at`. Records the environment's work on the arm measured on the segments' side."""
    segments = [FmuSlave(segment_fmu, f"segment{i + 1}") for i in range(n)]
    env = FmuSlave(environment_fmu, "environment", {"n_segments": n, **env_params})
    tau_env = np.zeros(n)
    work = 0.0
    record: dict[str, list] = {
        k: [] for k in ("work", "E_contact", "W_arm", "E_dissipated", "coupling_residual")
    }
    record.update(penetration=[], theta_dot=[])
    try:
        theta = np.array([s.get("theta") for s in segments])
        for k in range(int(round(duration / H))):
            t = k * H
            for i, s in enumerate(segments):
                env.set(f"kappa_{i + 1}", s.get("kappa"))
                env.set(f"theta_dot_{i + 1}", s.get("theta_dot"))
            applied = tau_env.copy()
            for i, s in enumerate(segments):
                push = drive[i] if drive is not None and t < release_at else 0.0
                s.set("tau_ext", push + applied[i])
                s.do_step(t, H)
            env.do_step(t, H)
            tau_env = np.array([env.get(f"tau_ext_{i + 1}") for i in range(n)])
            new_theta = np.array([s.get("theta") for s in segments])
            work += float(applied @ (new_theta - theta))
            theta = new_theta
            record["work"].append(work)
            for name in ("E_contact", "W_arm", "E_dissipated", "coupling_residual"):
                record[name].append(env.get(name))
            record["penetration"].append([env.get(f"penetration_{i + 1}") for i in range(n)])
            record["theta_dot"].append([s.get("theta_dot") for s in segments])
        result = {name: np.asarray(values) for name, values in record.items()}
        result["tau"] = tau_env
        result["theta"] = theta
        result["force"] = np.array([env.get(f"contact_force_{i + 1}") for i in range(n)])
        return result
    finally:
        for s in segments:
            s.close()
        env.close()


def test_a_passive_segment_pressed_into_a_wall_rests_at_penetration_force_over_stiffness(
    environment_fmu, segment_fmu
) -> None:
    # a straight segment, a wall 2 mm above its capsule near the tip, a constant bending torque
    params = {"mu_table": 0.0}
    with_wall(params, 1, [(0.04, 0.012), (0.1, 0.012)])
    r = coupled_run(environment_fmu, segment_fmu, 1, params, [0.005], 1.0)
    assert np.max(np.abs(r["theta_dot"][-100:])) < 1e-6  # at rest
    penetration = r["penetration"][-1, 0]
    assert 5e-5 < penetration < 1e-3
    # the force from the torque balance: the tip pushes up along dp/dtheta (kinematics.py)
    theta = r["theta"][0]
    tip = [
        kinematics.segment_end((0, 0, 0), th / LENGTH, LENGTH)[1]
        for th in (theta + 1e-7, theta - 1e-7)
    ]
    lever = (tip[0] - tip[1]) / 2e-7
    force = -r["tau"][0] / lever
    assert penetration == pytest.approx(force / K_CONTACT, rel=0.02)
    assert r["force"][0] == pytest.approx(force, rel=0.02)
    # and the geometry: the tip's capsule reaches the wall by exactly that penetration
    y_tip = kinematics.segment_end((0, 0, 0), theta / LENGTH, LENGTH)[1]
    assert y_tip + 0.01 - 0.012 == pytest.approx(penetration, rel=0.02)


WALL_ABOVE_THE_TIP = [(0.25, 0.015), (0.45, 0.015)]


def test_a_passive_six_segment_arm_pushed_into_a_wall_comes_to_rest(
    environment_fmu, segment_fmu
) -> None:
    # frictionless, so that only the contact, the springs and the push decide where it rests
    params: dict[str, float] = {"mu_table": 0.0, "mu_arm": 0.0}
    with_wall(params, 1, WALL_ABOVE_THE_TIP)
    r = coupled_run(environment_fmu, segment_fmu, 6, params, [0.01, 0, 0, 0, 0, 0], 1.2)
    assert np.max(r["penetration"]) < 2e-3
    # coming to rest: the bend rates decay (the segments' slow pole k / d ~ 4 1/s) to ~0
    speed = np.max(np.abs(r["theta_dot"]), axis=1)
    assert speed[-1] < 3e-3 and speed[-1] < 0.1 * speed[700] < 0.1 * 0.1 * speed[200]
    # resting on the wall with one point, at the penetration its force and k_contact set
    touching = np.flatnonzero(r["penetration"][-1] > 0.0)
    assert len(touching) == 1 and r["penetration"][-1, touching[0]] > 1e-6
    force = r["force"][touching[0]]
    assert r["penetration"][-1, touching[0]] == pytest.approx(force / K_CONTACT, rel=0.01)


@pytest.fixture(scope="module")
def six_segments_against_a_wall(environment_fmu, segment_fmu) -> dict[str, np.ndarray]:
    """A six-segment arm whose base is driven into a wall above its tip, released at 0.4 s;
    default friction on the table and the wall."""
    params: dict[str, float] = {}
    with_wall(params, 1, WALL_ABOVE_THE_TIP)
    drive = [0.01, 0, 0, 0, 0, 0]
    return coupled_run(environment_fmu, segment_fmu, 6, params, drive, 0.6, release_at=0.4)


def test_contact_never_adds_energy(six_segments_against_a_wall) -> None:
    r = six_segments_against_a_wall
    assert np.max(r["penetration"]) > 1e-5  # it did press into the wall
    assert np.max(r["coupling_residual"]) < 1e-9  # the implicit torque converged every step
    # its account of its work on the arm is the segments' own (it learns a step's angles at the
    # start of the next step, so it lags by one step)
    np.testing.assert_allclose(r["W_arm"][1:], r["work"][:-1], rtol=1e-9, atol=1e-15)
    # that work never exceeds the elastic energy the contact gives back (it started with none):
    # -W_arm - E_contact >= 0 at every step, both at the angles the arm reached
    absorbed = -r["W_arm"] - r["E_contact"]
    assert np.min(absorbed) > -1e-9
    dissipated = r["E_dissipated"]
    assert np.all(np.diff(dissipated) >= 0.0) and dissipated[-1] > 0.0
    # and its own estimate of what it dissipated is what it absorbed, within 10 %
    assert dissipated[-1] == pytest.approx(absorbed[-1], rel=0.1)


def test_a_frictionless_impact_returns_no_net_energy(environment_fmu, segment_fmu) -> None:
    # without friction only the contact's damping and the passivity controller dissipate; at the
    # impact the arm penetrates within the step before the torque answers, so the contact holds
    # energy it was not paid for, and its rebound may hand the arm a little of it until the
    # passivity controller takes it back: at most a small part of the impact's elastic energy
    params: dict[str, float] = {"mu_table": 0.0, "mu_arm": 0.0}
    with_wall(params, 1, WALL_ABOVE_THE_TIP)
    r = coupled_run(environment_fmu, segment_fmu, 6, params, [0.01, 0, 0, 0, 0, 0], 0.6, 0.4)
    assert np.max(r["E_contact"]) > 1e-4  # a real impact
    assert np.max(r["W_arm"]) < 0.03 * np.max(r["E_contact"])
    assert r["W_arm"][-1] < 0.0 and r["E_contact"][-1] == 0.0  # released: net absorbed


# ------------------------------------------------------------------ dissipation, objects


def test_dissipation_is_non_negative_over_a_random_trajectory(environment_fmu) -> None:
    rng = np.random.default_rng(2024)
    n, steps = 4, 600
    params: dict[str, float] = {
        "n_segments": n,
        "arm_mobility": 0.0,
        "coupling_delay": 0,
        "n_objects": 2,
        "object_x0_1": 0.2,
        "object_y0_1": 0.06,
        "object_x0_2": 0.16,
        "object_y0_2": -0.05,
        "mu_table": 0.3,
    }
    with_wall(params, 1, [(0.0, 0.08), (0.3, 0.08)])
    with_wall(params, 2, [(0.0, -0.07), (0.3, -0.07)])
    # smooth seeded curvature trajectories (sums of sines) and their exact bend rates
    amplitude = rng.uniform(2.0, 8.0, (n, 3))
    frequency = rng.uniform(0.5, 3.0, (n, 3))
    phase = rng.uniform(0.0, 2 * math.pi, (n, 3))

    def theta(t: float) -> np.ndarray:
        return LENGTH * np.sum(amplitude * np.sin(2 * math.pi * frequency * t + phase), axis=1)

    def theta_dot(t: float) -> np.ndarray:
        w = 2 * math.pi * frequency
        return LENGTH * np.sum(amplitude * w * np.cos(w * t + phase), axis=1)

    dissipated, balance = [], []
    with FmuSlave(environment_fmu, "env", params) as env:
        start = env.get("E_contact") + env.get("E_kinetic")
        for k in range(steps):
            t = k * H
            for i in range(n):
                env.set(f"kappa_{i + 1}", theta(t)[i] / LENGTH)
                env.set(f"theta_dot_{i + 1}", theta_dot(t)[i])
            env.do_step(t, H)
            dissipated.append(env.get("E_dissipated"))
            stored = env.get("E_contact") + env.get("E_kinetic") - start
            balance.append((-env.get("W_arm"), stored + dissipated[-1]))
        assert env.get("contact_impulse") > 0.0
    dissipated = np.asarray(dissipated)
    assert np.all(np.diff(dissipated) >= 0.0) and dissipated[-1] > 1e-4
    work_in, accounted = np.asarray(balance).T
    # the arm's work on the environment is what it stores plus what it dissipates (to the
    # discretisation of 1 ms steps of the arm's motion)
    assert abs(work_in[-1] - accounted[-1]) < 0.1 * dissipated[-1]


def test_an_object_pushed_by_the_arm_moves_and_stops_under_table_friction(
    environment_fmu,
) -> None:
    # one straight segment sweeps (prescribed bend) through a disk lying beside its tip
    params = {
        "n_segments": 1,
        "arm_mobility": 0.0,
        "coupling_delay": 0,
        "n_objects": 1,
        "object_x0_1": 0.055,
        "object_y0_1": 0.03,
        "object_radius_1": 0.015,
        "object_mass_1": 0.02,
        "mu_table_object": 0.3,
    }
    rate = 2.0  # rad/s for 0.3 s, then the segment stops
    x, vx, speed_max = [], [], 0.0
    with FmuSlave(environment_fmu, "env", params) as env:
        for k in range(800):
            t = k * H
            moving = t < 0.3
            bend = rate * min(t, 0.3)
            env.set("kappa_1", bend / LENGTH)
            env.set("theta_dot_1", rate if moving else 0.0)
            env.do_step(t, H)
            x.append((env.get("object_x_1"), env.get("object_y_1")))
            vx.append(math.hypot(env.get("object_vx_1"), env.get("object_vy_1")))
            speed_max = max(speed_max, vx[-1])
        assert env.get("W_objects") > 0.0
        kinetic = env.get("E_kinetic")
    x = np.asarray(x)
    moved = np.linalg.norm(x[-1] - x[0])
    assert moved > 5e-3 and speed_max > 0.01  # pushed
    assert vx[-1] == 0.0 and kinetic == 0.0  # stopped by Coulomb friction, exactly
    # once the arm has stopped (t = 0.3 s) and let go of it, it decelerates at mu g exactly
    free = [i for i in range(300, len(vx) - 1) if vx[i + 1] > 0.0]
    assert free, "the object was still sliding when the arm stopped"
    np.testing.assert_allclose(
        np.diff(np.asarray(vx)[free[0] : free[-1] + 2]), -0.3 * 9.81 * H, rtol=1e-9
    )


def test_an_object_placed_into_a_wall_is_pushed_out_along_its_normal(environment_fmu) -> None:
    # a disk 1 mm deep in a wall along y = 0, far from the arm: the wall's spring pushes it out
    params = {
        "n_segments": 1,
        "n_objects": 1,
        "object_x0_1": 0.2,
        "object_y0_1": 0.014,
        "object_radius_1": 0.015,
    }
    with_wall(params, 1, [(0.1, 0.0), (0.3, 0.0)])
    with FmuSlave(environment_fmu, "env", params) as env:
        stored = env.get("E_contact")
        assert stored == pytest.approx(0.5 * K_CONTACT * 1e-3**2, rel=1e-9)
        for k in range(50):
            env.do_step(k * H, H)
        assert env.get("E_contact") == 0.0 and env.get("W_arm") == 0.0
        assert env.get("object_y_1") > 0.015 and env.get("object_vy_1") > 0.0
        assert env.get("object_x_1") == 0.2 and env.get("object_yaw_1") == 0.0  # along the normal
        # the spring's energy became motion, contact damping and table friction
        accounted = env.get("E_kinetic") + env.get("E_dissipated")
        assert accounted == pytest.approx(stored, rel=0.02)
        # the contact's work on the disk is its kinetic energy plus what the table took, and
        # less than the spring held by what the contact's damping took
        assert env.get("E_kinetic") < env.get("W_objects") < stored


@pytest.mark.parametrize("k_contact", [300.0, 1000.0])
@pytest.mark.parametrize("offset", [0.0, 1e-16, 1e-3])
def test_an_object_started_deep_in_the_arm_leaves_with_at_most_the_penalty_energy(
    environment_fmu, k_contact: float, offset: float
) -> None:
    """A 5 g disk placed 20 mm deep in a straight arm held at rest (its centre `offset` off the
    backbone; six sample points reach it): the penetrations' elastic energy is all the
    environment holds, so the disk can take at most that as kinetic energy. The objects'
    substeps are explicit in the Hunt-Crossley damping: at this depth it was 12 times what a
    substep resolves, and the disk left at 700 m/s (thousands of joules) from 0.15 J."""
    params = {
        "n_segments": 6,
        "n_objects": 1,
        "object_x0_1": 0.05,
        "object_y0_1": offset,
        "object_radius_1": 0.0125,
        "object_mass_1": 0.005,
        "k_contact": k_contact,
    }
    kinetic = []
    with FmuSlave(environment_fmu, "env", params) as env:
        stored = env.get("E_contact")
        assert stored > 0.1 * k_contact / 300.0  # deep: about 0.15 J at 300 N/m
        for k in range(100):
            env.do_step(k * H, H)
            kinetic.append(env.get("E_kinetic"))
            assert env.get("E_contact") + kinetic[-1] <= stored, f"step {k}"
        assert env.get("W_arm") == 0.0  # the arm is held: the penetration is the only source
    assert max(kinetic) <= stored


def test_an_arm_started_deep_in_a_wall_gets_at_most_the_penalty_energy(
    environment_fmu, segment_fmu
) -> None:
    """The arm's side of a deep start: a straight six-segment arm with a frictionless wall 9 mm
    deep across four segments. The implicit coupling pushes it out; the work of the torques on
    the arm never exceeds the elastic energy the penetration held."""
    params: dict[str, float] = {"mu_table": 0.0, "mu_arm": 0.0}
    with_wall(params, 1, [(0.1, 0.001), (0.3, 0.001)])
    r = coupled_run(environment_fmu, segment_fmu, 6, params, None, 0.3)
    stored = r["E_contact"][0]
    assert stored > 1.0  # deep: 1.1 J
    assert np.max(r["W_arm"]) <= stored
    assert np.max(r["penetration"][-1]) < 1e-3  # out of the wall


# ------------------------------------------------------------------ FMU, spec, estimates


def test_fmpy_validation_and_a_short_simulation_pass() -> None:
    assert main(["fmu", "check", "Environment", "--stop-time", "0.05", "--step", "0.001"]) == 0


def test_indexed_families_declare_consecutive_members() -> None:
    spec = load_spec(fmus.source_root() / "Environment")
    names = [v.name for v in spec.variables]
    first = names.index("kappa_1")
    assert names[first : first + 7] == [f"kappa_{i}" for i in range(1, 8)]
    refs = [spec.variable(f"kappa_{i}").value_reference for i in range(1, 8)]
    assert refs == list(range(refs[0], refs[0] + 7))
    assert spec.variable("kappa_3").description == "Curvature of segment 3"
    assert dict(spec.families)["wall1_x"] == 16
    # a family in depends_on names all its members
    assert set(spec.variable("tau_ext_2").depends_on) >= {f"kappa_{i}" for i in range(1, 8)}


def test_an_indexed_family_takes_a_start_per_member(tmp_path) -> None:
    folder = tmp_path / "Fam"
    folder.mkdir()
    (folder / "model.toml").write_text(
        '[model]\nname = "Fam"\n[parameters.x]\ncount = 3\nstart = [1.0, 2.0, 3.0]\n'
        'description = "x of {i}"\n[parameters.y]\nstart = 0.0\n'
    )
    spec = load_spec(folder)
    assert [(v.name, v.start, v.value_reference) for v in spec.variables] == [
        ("x_1", 1.0, 0),
        ("x_2", 2.0, 1),
        ("x_3", 3.0, 2),
        ("y", 0.0, 3),
    ]
    assert spec.variable("x_2").description == "x of 2"
    assert "#define COUNT_x 3" in generate_header(spec, "{guid}")


def test_an_indexed_family_with_a_bad_start_list_is_one_line_error(tmp_path) -> None:
    folder = tmp_path / "Bad"
    folder.mkdir()
    (folder / "model.toml").write_text(
        '[model]\nname = "Bad"\n[parameters.x]\ncount = 3\nstart = [1.0, 2.0]\n'
    )
    with pytest.raises(BuildError, match=r"parameters.x.start has 2 values for count = 3"):
        load_spec(folder)


def test_inertial_coupling_estimate_of_the_header_note() -> None:
    # the PCC mass matrix of a straight six-segment arm (0.03 kg, 0.06 m per segment), from
    # kinematics.py by finite differences: what each FeaSegment's m L^2 / 20 leaves out
    n, samples, mass = 6, 64, 0.03

    def points(theta: np.ndarray) -> np.ndarray:
        out, pose = [], (0.0, 0.0, 0.0)
        for j in range(n):
            for k in range(samples):
                s = LENGTH * (k + 0.5) / samples
                out.append(kinematics.segment_end(pose, theta[j] / LENGTH, s)[:2])
            pose = kinematics.segment_end(pose, theta[j] / LENGTH, LENGTH)
        return np.array(out)

    e = 1e-7
    J = np.stack(
        [(points(e * np.eye(n)[i]) - points(-e * np.eye(n)[i])) / (2 * e) for i in range(n)], -1
    )
    M = (mass / samples) * np.einsum("pai,paj->ij", J, J)
    modelled = mass * LENGTH**2 / 20
    assert M[-1, -1] == pytest.approx(modelled, rel=0.01)  # the tip segment is what FeaSegment has
    assert M[0, 0] == pytest.approx(6.1e-3, rel=0.02)  # the header's figure
    assert M[0, 0] / 6e-3 == pytest.approx(1.0, rel=0.05)  # base time constant M_11 / d [s]
    friction_per_mu = 9.81 * (mass / samples) * np.linalg.norm(J[:, :, 0], axis=1).sum()
    assert friction_per_mu == pytest.approx(0.27, rel=0.01)  # the header's figure
