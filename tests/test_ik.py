"""Tests for robots.planar_arm.controller.ik (task-space IK on curvatures) and the curvature bounds
it is given,
SegmentModel.reachable_curvature, checked against the FeaSegment FMU's steady state.

Oracles: forward kinematics (a solution is a tip on the target), the first-order optimality of
the least-bending solution (its gradient lies in the Jacobian's row space), geometry of the
straight arm, and for the bounds the FMU simulated to rest.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from controllers.curvature import SegmentModel
from controllers.kinematics import forward, tip_jacobian
from robots.planar_arm.controller.ik import ik_step, reachable, sample_workspace, solve_ik
from tests.helpers import simulate

N = 6
LENGTHS = np.full(N, 0.06)  # [m]
BASE = (0.0, 0.0, math.pi / 2)  # the arm points along +y
LOWER, UPPER = np.full(N, -20.0), np.full(N, 24.0)  # [1/m] an asymmetric range


def tip(kappas: np.ndarray, lengths: np.ndarray = LENGTHS) -> np.ndarray:
    return forward(kappas, lengths, BASE)[-1]


def workspace(n: int, seed: int, margin: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    return sample_workspace(np.random.default_rng(seed), LENGTHS, BASE, LOWER, UPPER, n, margin)


def null_space_residual(kappas: np.ndarray) -> float:
    """|(I - J^+ J) theta| in bend angles: zero where ||theta||^2 is stationary on the set of
    configurations with this tip position."""
    jacobian = tip_jacobian(kappas, LENGTHS, BASE)[:2] / LENGTHS
    theta = kappas * LENGTHS
    return float(np.linalg.norm(theta - np.linalg.pinv(jacobian) @ (jacobian @ theta)))


# ---------------------------------------------------------------- solve_ik


def test_reaches_sampled_targets_from_several_starts() -> None:
    poses, _ = workspace(6, seed=1)
    starts = (np.zeros(N), 0.5 * LOWER, 0.5 * UPPER)
    for target in poses[:, :2]:
        for start in starts:
            result = solve_ik(target, start, LENGTHS, BASE, LOWER, UPPER)
            assert result.converged, (target, start)
            assert result.position_error < 1e-6
            assert np.linalg.norm(tip(result.kappas)[:2] - target) == pytest.approx(
                result.position_error, abs=1e-15
            )
            assert np.all(result.kappas >= LOWER) and np.all(result.kappas <= UPPER)
            assert not result.saturated.any()


def test_redundancy_resolves_to_the_least_bending_solution() -> None:
    # first-order optimality of min ||theta||^2 subject to the tip: theta in J's row space; and
    # the same answer from rest and from the configuration that drew the target (rest, not the
    # start, decides it; a start bent the opposite way may settle on the mirrored S-shape, the
    # other local optimum)
    poses, drawn = workspace(4, seed=2)
    for target, kappas_drawn in zip(poses[:, :2], drawn, strict=True):
        answers = [
            solve_ik(target, start, LENGTHS, BASE, LOWER, UPPER).kappas
            for start in (np.zeros(N), kappas_drawn, 0.5 * kappas_drawn)
        ]
        assert null_space_residual(kappas_drawn) > 1e-2  # the drawn one is not it
        for kappas in answers:
            assert null_space_residual(kappas) < 1e-7
            np.testing.assert_allclose(kappas, answers[0], rtol=0.0, atol=1e-6)


def test_rest_shifts_the_answer_but_not_the_tip() -> None:
    target = tip(np.array([10.0, 5.0, -3.0, 8.0, 2.0, 1.0]))[:2]
    rest = np.array([15.0, 15.0, 15.0, 0.0, 0.0, 0.0])
    plain = solve_ik(target, np.zeros(N), LENGTHS, BASE, LOWER, UPPER)
    shifted = solve_ik(target, np.zeros(N), LENGTHS, BASE, LOWER, UPPER, rest=rest)
    assert plain.converged and shifted.converged
    # the stationarity law with rest: theta - theta_rest in the row space
    jacobian = tip_jacobian(shifted.kappas, LENGTHS, BASE)[:2] / LENGTHS
    offset = (shifted.kappas - rest) * LENGTHS
    assert np.linalg.norm(offset - np.linalg.pinv(jacobian) @ (jacobian @ offset)) < 1e-7
    assert np.linalg.norm((shifted.kappas - rest)[:3]) < np.linalg.norm((plain.kappas - rest)[:3])


def test_answer_moves_continuously_with_the_target() -> None:
    # warm-started along a line of targets 1 mm apart, the curvatures move by a bounded amount
    # per millimetre (no jumps between branches)
    start, end = np.array([-0.12, 0.25]), np.array([0.12, 0.25])
    kappas = np.zeros(N)
    previous = None
    for fraction in np.linspace(0.0, 1.0, 25):
        result = solve_ik(start + fraction * (end - start), kappas, LENGTHS, BASE, LOWER, UPPER)
        assert result.converged
        if previous is not None:
            assert np.max(np.abs(result.kappas - previous)) * 0.06 < 0.05  # [rad] per 10 mm
        previous = kappas = result.kappas


@pytest.mark.parametrize("target", [(0.0, 0.3), (0.0, 0.2), (0.05, 0.34), (-0.001, 0.35)])
def test_works_from_the_straight_singular_configuration(target: tuple[float, float]) -> None:
    # straight ahead and nearer than the arm's 0.36 m, the error is orthogonal to every column
    result = solve_ik(target, np.zeros(N), LENGTHS, BASE, LOWER, UPPER)
    assert result.converged and result.position_error < 1e-6


def test_beyond_reach_straight_ahead_stays_straight() -> None:
    result = solve_ik((0.0, 0.5), np.zeros(N), LENGTHS, BASE, LOWER, UPPER)
    assert not result.converged
    np.testing.assert_array_equal(result.kappas, np.zeros(N))
    assert result.position_error == pytest.approx(0.5 - 0.36, rel=1e-12)


def test_target_beyond_the_bounds_ends_saturated_with_its_error() -> None:
    # with |kappa| <= 3 1/m the arm cannot curl to a target beside its base
    lower, upper = np.full(N, -3.0), np.full(N, 3.0)
    result = solve_ik((0.2, 0.0), np.zeros(N), LENGTHS, BASE, lower, upper)
    assert not result.converged and result.saturated.all()
    np.testing.assert_array_equal(result.kappas, lower)  # all bending towards it, to the limit
    expected = np.linalg.norm(tip(lower)[:2] - (0.2, 0.0))
    assert result.position_error == pytest.approx(expected, rel=1e-12)


def test_saturated_segment_leaves_the_rest_to_the_others() -> None:
    # segment 0 may bend left only to 3 1/m, less than the least-bending answer asks of it:
    # it is held at the bound and the others reach the target
    lower, upper = LOWER.copy(), UPPER.copy()
    upper[0] = 3.0
    drawn = np.array([0.0, 12.0, 12.0, 8.0, 0.0, 0.0])
    target = tip(drawn)[:2]
    unbounded = solve_ik(target, np.zeros(N), LENGTHS, BASE, LOWER, UPPER)
    assert unbounded.kappas[0] > 3.5
    # from rest, and from the drawn configuration, where the task is met at once and only the
    # pull towards rest (here towards segment 0's bound) moves it
    for start in (np.zeros(N), drawn):
        result = solve_ik(target, start, LENGTHS, BASE, lower, upper)
        assert result.converged
        assert result.kappas[0] == 3.0 and result.saturated[0] and not result.saturated[1:].any()
        assert np.all(result.kappas >= lower) and np.all(result.kappas <= upper)


def test_heading_option_reaches_position_and_heading() -> None:
    poses, _ = workspace(6, seed=3)
    for pose in poses:
        result = solve_ik(pose[:2], np.zeros(N), LENGTHS, BASE, LOWER, UPPER, heading=pose[2])
        assert result.converged, pose
        assert result.position_error < 1e-6 and abs(result.heading_error) < 1e-6
        assert math.remainder(tip(result.kappas)[2] - pose[2], 2 * math.pi) == pytest.approx(
            0.0, abs=1e-6
        )


def test_heading_is_compared_modulo_a_full_turn() -> None:
    kappas = np.array([5.0, 5.0, 5.0, 5.0, 5.0, 5.0])
    pose = tip(kappas)
    result = solve_ik(
        pose[:2], np.zeros(N), LENGTHS, BASE, LOWER, UPPER, heading=pose[2] + 2 * math.pi
    )
    assert result.converged and abs(result.heading_error) < 1e-6


def test_bad_bounds_are_rejected() -> None:
    with pytest.raises(ValueError, match="segment 2: lower curvature bound above the upper"):
        solve_ik((0.0, 0.3), np.zeros(N), LENGTHS, BASE, LOWER, np.where(np.arange(N) == 2, -21, 5))
    with pytest.raises(ValueError, match="bounds of 5 and 6 segments"):
        solve_ik((0.0, 0.3), np.zeros(N), LENGTHS, BASE, LOWER[:5], UPPER)


# ---------------------------------------------------------------- ik_step (the control loop)


def test_repeated_steps_on_a_perfect_plant_converge_within_the_rate_limit() -> None:
    poses, _ = workspace(3, seed=4)
    for target in poses[:, :2]:
        kappas = np.zeros(N)
        for _ in range(50):
            error = target - tip(kappas)[:2]
            new = ik_step(kappas, error, LENGTHS, BASE, LOWER, UPPER, max_step=2.0)
            assert np.max(np.abs(new - kappas)) <= 2.0 * (1 + 1e-12)
            assert np.all(new >= LOWER) and np.all(new <= UPPER)
            kappas = new
        assert np.linalg.norm(target - tip(kappas)[:2]) < 1e-6


def test_step_converges_quadratically_away_from_singularities() -> None:
    # Gauss-Newton (no damping where the Jacobian is well conditioned): the error left after
    # one step from a small error d shrinks as d^2, not in proportion to d
    kappas = np.array([6.0, 8.0, 9.0, 7.0, 5.0, 2.0])
    ratios = []
    for d in (1e-5, 1e-6):
        error = np.array([d, -d]) / math.sqrt(2)
        new = ik_step(kappas, error, LENGTHS, BASE, LOWER, UPPER, rest_weight=0.0)
        left = np.linalg.norm(tip(kappas)[:2] + error - tip(new)[:2])
        ratios.append(left / d)
    assert ratios[0] < 1e-3
    assert ratios[1] == pytest.approx(0.1 * ratios[0], rel=0.05)


def test_rate_limit_keeps_the_step_direction() -> None:
    kappas = np.array([2.0, -1.0, 3.0, 0.5, 0.0, 1.0])
    error = np.array([-0.05, -0.02])
    free = ik_step(kappas, error, LENGTHS, BASE, LOWER, UPPER)
    limited = ik_step(kappas, error, LENGTHS, BASE, LOWER, UPPER, max_step=0.1)
    assert np.max(np.abs(limited - kappas)) == pytest.approx(0.1, rel=1e-12)
    direction = (free - kappas) / np.linalg.norm(free - kappas)
    np.testing.assert_allclose(
        (limited - kappas) / np.linalg.norm(limited - kappas), direction, atol=1e-12
    )


def test_step_from_the_straight_arm_towards_a_nearer_target_bends_it() -> None:
    error = np.array([0.0, -0.05])  # straight ahead, 5 cm nearer
    new = ik_step(np.zeros(N), error, LENGTHS, BASE, LOWER, UPPER)
    assert np.linalg.norm((0.0, 0.31) - tip(new)[:2]) < 0.05


def test_step_holds_a_segment_at_its_bound_and_moves_the_others() -> None:
    kappas = np.array([24.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    # pushing further left than segment 0 may bend
    new = ik_step(kappas, np.array([-0.05, 0.0]), LENGTHS, BASE, LOWER, UPPER)
    assert new[0] == 24.0 and np.any(new[1:] > 0.0)


def test_heading_step_turns_the_tip() -> None:
    new = ik_step(np.zeros(N), np.zeros(2), LENGTHS, BASE, LOWER, UPPER, heading_error=0.2)
    turn = tip(new)[2] - BASE[2]
    assert 0.0 < turn <= 0.2 + 1e-9


# ---------------------------------------------------------------- workspace


def test_sampled_targets_are_reachable_inside_the_shrunk_bounds() -> None:
    poses, kappas = workspace(20, seed=5, margin=0.25)
    assert poses.shape == (20, 3) and kappas.shape == (20, N)
    span = UPPER - LOWER
    assert np.all(kappas >= LOWER + 0.25 * span) and np.all(kappas <= UPPER - 0.25 * span)
    for pose, k in zip(poses, kappas, strict=True):
        np.testing.assert_array_equal(pose, tip(k))
    assert all(reachable(pose[:2], LENGTHS, BASE, LOWER, UPPER) for pose in poses[:2])
    assert not reachable((0.0, 0.37), LENGTHS, BASE, LOWER, UPPER)  # beyond the arm's length
    narrow = np.full(N, 3.0)
    assert not reachable((0.2, 0.0), LENGTHS, BASE, -narrow, narrow)  # beyond the bounds
    with pytest.raises(ValueError, match="margin = 0.5"):
        workspace(1, seed=0, margin=0.5)


def test_sampling_is_seeded() -> None:
    np.testing.assert_array_equal(workspace(4, seed=7)[0], workspace(4, seed=7)[0])


# ---------------------------------------------------------------- curvature bounds from physics


ASYMMETRIC = {"k_bend": 0.05, "x_seal": 0.02}  # stiffer (off the limit), sealed off-centre


@pytest.mark.parametrize("parameters", [{}, ASYMMETRIC], ids=["defaults", "asymmetric"])
def test_reachable_curvature_is_the_fmu_steady_state_at_full_stroke(
    fea_segment_fmu, parameters: dict[str, float]
) -> None:
    model = SegmentModel(**parameters)
    kappa_min, kappa_max = model.reachable_curvature()
    for x_piston, expected in ((0.0, kappa_min), (model.stroke, kappa_max)):
        # the defaults press against the limit within a second; the stiffer segment relaxes
        # with its slow pole (k + k_gas) / d ~ 9 1/s, so by 2 s it is at rest to ~1e-8
        r = simulate(
            fea_segment_fmu,
            2.0,
            ["kappa", "theta_dot"],
            parameters,
            lambda t, x=x_piston: {"x_piston": x},
            step=0.02,
        )
        assert abs(r["theta_dot"][-1]) < 1e-6
        assert r["kappa"][-1] == pytest.approx(expected, rel=1e-6)
    # the piston towards the end of the stroke bends positively
    assert kappa_min < 0.0 < kappa_max


def test_defaults_reach_the_mechanical_limit_both_ways() -> None:
    assert SegmentModel().reachable_curvature() == (-1.6 / 0.06, 1.6 / 0.06)


def test_sealing_off_centre_makes_the_range_asymmetric_and_vacuum_narrows_it() -> None:
    kappa_min, kappa_max = SegmentModel(**ASYMMETRIC).reachable_curvature()
    # sealed at x = 0.02 the stroke is 0.02 one way and 0.03 the other
    assert -kappa_min < kappa_max
    full = SegmentModel(**ASYMMETRIC, vacuum_factor=1.0).reachable_curvature()
    # the collapsing channel under vacuum pulls less, so each end bends less
    assert full[0] < kappa_min and kappa_max < full[1]


def test_equilibrium_slope_at_sealing_is_the_linearised_gain() -> None:
    # without the collapse the balance is smooth: central differences give the linear gain to
    # O(h^2); with it the vacuum side's torque G_a (g + (1 - f) g^2 / (2 p_c)) has a second
    # derivative that jumps at g = 0, so the difference quotient approaches the gain as O(h)
    def slope(model: SegmentModel, h: float) -> float:
        up = model.equilibrium_curvature(model.x_seal + h)
        down = model.equilibrium_curvature(model.x_seal - h)
        return (up - down) / (2 * h)

    smooth = SegmentModel(k_bend=0.05, vacuum_factor=1.0)
    assert smooth.equilibrium_curvature(smooth.x_seal) == pytest.approx(0.0, abs=1e-9)
    assert slope(smooth, 1e-5) == pytest.approx(smooth.static_gain(), rel=1e-7)
    model = SegmentModel(k_bend=0.05)
    deviations = [slope(model, h) / model.static_gain() - 1 for h in (1e-5, 1e-6)]
    assert -1e-3 < deviations[0] < 0.0  # the collapse weakens the bend both ways
    assert deviations[0] / deviations[1] == pytest.approx(10.0, rel=0.01)


def test_equilibrium_rises_with_the_piston_and_balances_torque() -> None:
    model = SegmentModel(**ASYMMETRIC)
    xs = np.linspace(0.0, model.stroke, 11)
    kappas = [model.equilibrium_curvature(float(x)) for x in xs]
    assert np.all(np.diff(kappas) > 0.0)
    for x, kappa in zip(xs, kappas, strict=True):
        assert model.net_torque(float(x), kappa * model.length) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("x_piston", [-1e-3, 0.051])
def test_equilibrium_outside_the_stroke_is_an_error(x_piston: float) -> None:
    with pytest.raises(ValueError, match="x_piston = "):
        SegmentModel().equilibrium_curvature(x_piston)
