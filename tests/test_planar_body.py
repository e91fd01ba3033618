"""The planar arm on the multibody ArmBody FMU (robot.model = "body"): the rig wires one body for
every segment, the base bend carries the whole outer arm's inertia, and what the body cannot
carry fails naming its key."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil.errors import ScenarioError
from hil.rig import build_rig
from hil.scenario import load_scenario

LENGTHS = (0.06, 0.05, 0.07, 0.06, 0.04, 0.06)
MASSES = (0.03, 0.025, 0.035, 0.03, 0.02, 0.03)
SIX = f"""
name = "six"
seed = 1
duration = 0.2
[robot]
segments = 6
model = "body"
[robot.segment]
length = {list(LENGTHS)}
mass = {list(MASSES)}
[task]
steps = [[0.0, 0.0]]
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path


def hand_count_base_inertia(lengths: tuple[float, ...], masses: tuple[float, ...]) -> float:
    """The base bend's inertia of the straight arm counted by hand: sum over the arm's mass of
    m r^2, r the sideways lever of each mass element per base bend angle. A PCC bend is no
    joint at the base: bending segment 1 by a small angle moves its own arc's point at s by
    s^2 / (2 L_1) and turns everything beyond about the middle of its arc, so r = s^2 / (2 L_1)
    on segment 1 (its m L_1^2 / 20) and r = distance - L_1 / 2 beyond (a uniform segment j of
    mass m_j centred at c_j from the base: m_j ((c_j - L_1 / 2)^2 + L_j^2 / 12))."""
    total = masses[0] * lengths[0] ** 2 / 20.0
    start = lengths[0]
    for length, mass in zip(lengths[1:], masses[1:], strict=True):
        centre = start + length / 2.0
        total += mass * ((centre - lengths[0] / 2.0) ** 2 + length**2 / 12.0)
        start += length
    return total


def test_the_base_bend_carries_the_whole_outer_arm(tmp_path: Path) -> None:
    """Through the planar rig: the body's M_11 at the straight start equals the hand count to
    1e-9, is the outer arm's (over 900 times the lone segment's m L^2 / 20), and is not
    the moment of inertia about the base point (a joint's), which overstates it."""
    from hil.cosim import Algorithm

    scenario = load_scenario(write(tmp_path, SIX))
    rig = build_rig(scenario)
    try:
        names = {getattr(p, "name", "") for p in rig.participants}
        assert "body" in names and not any(n.startswith("segment") for n in names)
        master = Algorithm(rig.participants, rig.connections, scenario.timing.step)
        base_inertia = master.values["body.M_11"]
        master.advance_to(5)
        assert all(master.values[f"body.theta_x_{n}"] == 0.0 for n in range(1, 7))
    finally:
        rig.close()
    expected = hand_count_base_inertia(LENGTHS, MASSES)
    assert base_inertia == pytest.approx(expected, rel=1e-9)
    assert base_inertia / (MASSES[0] * LENGTHS[0] ** 2 / 20.0) > 900.0
    about_base = sum(
        m * ((sum(LENGTHS[:j]) + L / 2.0) ** 2 + L**2 / 12.0)
        for j, (L, m) in enumerate(zip(LENGTHS, MASSES, strict=True))
    )
    assert about_base > 1.3 * base_inertia


def test_the_rig_maps_each_segment_onto_the_body(tmp_path: Path) -> None:
    """Per segment n: L_n, mass_n, k_n, d_n, G_a_n, theta_x_start_n from the resolved segment,
    no end pieces or endplates, the shared circuit from the cylinders, gravity normal to the
    plane; the recorded columns read the body; pistons and pressures wired both ways."""
    text = SIX.replace("[task]", "[robot.segment.3]\nk_bend = 0.04\ntheta_start = 0.3\n[task]")
    scenario = load_scenario(write(tmp_path, text))
    rig = build_rig(scenario)
    try:
        values = rig.parameters["body"]
        sources = {c.target: c.source for c in rig.connections}
        signals = {s.column: s.source for s in rig.signals}
    finally:
        rig.close()
    assert values["n_segments"] == 6 and values["planar"] == 1
    assert [values[f"L_{n}"] for n in range(1, 7)] == list(LENGTHS)
    assert [values[f"mass_{n}"] for n in range(1, 7)] == list(MASSES)
    assert values["k_3"] == 0.04 and values["k_1"] == 0.025 and values["d_2"] == 6e-3
    assert values["theta_x_start_3"] == 0.3 and values["theta_x_start_1"] == 0.0
    assert all(values[f"L_p_{n}"] == 0.0 and values[f"m_end_{n}"] == 0.0 for n in range(1, 7))
    assert (values["g_x"], values["g_y"], values["g_z"]) == (0.0, -9.81, 0.0)
    assert (values["bore"], values["stroke"], values["x_seal"]) == (0.0254, 0.05, 0.025)
    assert values["substep"] == 0.0  # the body's own stability limit
    for n in range(1, 7):
        assert sources[f"body.x_piston_x_{n}"] == f"cylinder{n}.x"
        assert sources[f"cylinder{n}.p_a"] == f"body.p_a_x_{n}"
        assert sources[f"drive{n}.p_b"] == f"body.p_b_x_{n}"
        assert sources[f"camera.kappa_{n}"] == f"body.kappa_x_{n}"
        assert signals[f"kappa_{n}"] == f"body.kappa_x_{n}"
        assert signals[f"theta_{n}"] == f"body.theta_x_{n}"


def test_a_bent_start_is_held_on_the_body(tmp_path: Path) -> None:
    """theta_start puts the body's bend there and its piston where that bend is the static
    equilibrium: held 0.1 s by the drives, the signed curvatures stay."""
    from hil.cosim import Algorithm

    text = (
        SIX.split("[task]")[0].replace(
            "[robot.segment]\n", "[robot.segment]\ntheta_start = [0.6, -0.4, 0.0, 0.0, 0.0, 0.0]\n"
        )
        + "[task]\nsteps = [[0.0, 0.0]]\n"
    )
    scenario = load_scenario(write(tmp_path, text))
    rig = build_rig(scenario)
    try:
        master = Algorithm(rig.participants, rig.connections, scenario.timing.step)
        bent = [master.values[f"body.kappa_x_{n}"] for n in range(1, 7)]
        base_inertia = master.values["body.M_11"]
        master.advance_to(100)
        kappa = [master.values[f"body.kappa_x_{n}"] for n in (1, 2, 3)]
    finally:
        rig.close()
    assert kappa == pytest.approx([0.6 / LENGTHS[0], -0.4 / LENGTHS[1], 0.0], abs=0.05)
    # the mass matrix the controller schedules its loops on is the body's, bent as well
    from controllers.kinematics import mass_matrix

    assert bent[:2] == pytest.approx([0.6 / LENGTHS[0], -0.4 / LENGTHS[1]], rel=1e-12)
    controller_side = mass_matrix(bent, LENGTHS, MASSES)[0, 0]
    assert controller_side == pytest.approx(base_inertia, rel=1e-9)
    assert base_inertia < 0.99 * hand_count_base_inertia(LENGTHS, MASSES)  # bent: less


@pytest.mark.parametrize(
    ("extra", "key", "reason"),
    [
        ("[robot.segment]\nn_poly = 1.4\n", "robot.segment.n_poly", "isothermal"),
        ("[robot.segment]\nleak_conductance = 1e-9\n", "robot.segment.leak_conductance", "sealed"),
        ("[robot.segment]\nV_dead = [5e-6, 5e-6, 6e-6]\n", r"robot.segment.V_dead\[2\]", "differs"),
        ("[robot.segment.2]\ntheta_max = 1.2\n", "robot.segment.2.theta_max", "differs"),
        ("[robot.cylinder.3]\nbore = 0.02\n", "robot.cylinder.bore", "differs"),
        ("[robot.segment]\nsubstep = 5e-4\n", "robot.segment.substep", "stability limit"),
    ],
)
def test_what_the_body_cannot_carry_fails_naming_its_key(
    tmp_path: Path, extra: str, key: str, reason: str
) -> None:
    text = (
        'name = "x"\nseed = 1\nduration = 0.1\n[robot]\nsegments = 3\nmodel = "body"\n'
        + extra
        + "[task]\nsteps = [[0.0, 0.0]]\n"
    )
    with pytest.raises(ScenarioError, match=rf"s\.toml: {key}: .*{reason}"):
        load_scenario(write(tmp_path, text))


def test_the_segments_model_keeps_one_fmu_per_segment(tmp_path: Path) -> None:
    text = SIX.replace('model = "body"', 'model = "segments"')
    rig = build_rig(load_scenario(write(tmp_path, text)))
    try:
        names = {getattr(p, "name", "") for p in rig.participants}
    finally:
        rig.close()
    assert {f"segment{n}" for n in range(1, 7)} <= names and "body" not in names


def test_the_body_mass_matrix_the_controller_is_told_is_the_bodys() -> None:
    """The straight arm's mass matrix the controller designs against (robots.planar_arm.plant
    .body.mass_matrix) has the hand count on its diagonal corner and is symmetric positive
    definite."""
    from robots.planar_arm.plant.body import bend_inertias, mass_matrix

    M = np.array(mass_matrix(LENGTHS, MASSES))
    assert M[0, 0] == pytest.approx(hand_count_base_inertia(LENGTHS, MASSES), rel=1e-12)
    assert np.diag(M) == pytest.approx(bend_inertias(LENGTHS, MASSES), rel=1e-12)
    assert np.allclose(M, M.T) and min(np.linalg.eigvalsh(M)) > 0.0
    assert M[-1, -1] == pytest.approx(MASSES[-1] * LENGTHS[-1] ** 2 / 20.0, rel=1e-12)
