"""The curvature loops of a multibody arm (controllers.curvature.ArmGains, controllers.loop_design
.arm_loop_gains) and the coupled bend prediction of its estimator (controllers.bend_filter
.CoupledBends): without inertia they are the per-segment PI and filter exactly; on the
six-segment planar arm the per-segment PI is unstable and the arm's loops damp every mode."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import expm

from controllers.bend_filter import BendDiscretiser, CoupledBends
from controllers.curvature import ArmGains, SegmentModel
from controllers.estimation import BendModel
from controllers.kinematics import mass_matrix
from controllers.loop_design import arm_loop_gains, outer_loop_gains

N = 6
MODEL = SegmentModel()  # the rectangular segment: 60 mm, the FeaSegment defaults
MASS = 0.03
PERIOD = 0.01
DRIVE_LAG = 1.0 / (2.0 * math.pi * 10.0)  # the drive's position servo, >= 10 Hz


def closed_loop_poles(gains: ArmGains | None, mass_scale: float = 1.0) -> np.ndarray:
    """Continuous poles [1/s] of the straight six-segment arm (linearised at the seal: M theta''
    + D theta' + K theta = T x) under the loops sampled every PERIOD, the command acting one
    period late through the drive's first-order lag, the state known; `gains` None: the
    per-segment PIs of `outer_loop_gains`."""
    lengths = [MODEL.length] * N
    M = mass_matrix([0.0] * N, lengths, [MASS * mass_scale] * N)
    k = MODEL.k_bend + MODEL.gas_stiffness()
    torque = MODEL.static_gain() * MODEL.length * k
    A = np.zeros((3 * N, 3 * N))
    A[:N, N : 2 * N] = np.eye(N)
    A[N : 2 * N, :N] = -np.linalg.solve(M, k * np.eye(N))
    A[N : 2 * N, N : 2 * N] = -np.linalg.solve(M, MODEL.d_bend * np.eye(N))
    A[N : 2 * N, 2 * N :] = np.linalg.solve(M, torque * np.eye(N))
    A[2 * N :, 2 * N :] = -np.eye(N) / DRIVE_LAG
    augmented = np.zeros((4 * N, 4 * N))
    augmented[: 3 * N, : 3 * N] = A
    augmented[2 * N : 3 * N, 3 * N :] = np.eye(N) / DRIVE_LAG
    step = expm(augmented * PERIOD)
    F, G = step[: 3 * N, : 3 * N], step[: 3 * N, 3 * N :]
    # the loops' matrices in curvatures, read off their terms (they are linear)
    if gains is None:
        pi = outer_loop_gains(MODEL, 0.015, max_crossover_hz=1.0)
        Kp, Ki, Kd = pi.Kp * np.eye(N), pi.Ki * np.eye(N), np.zeros((N, N))
    else:
        zero = [0.0] * N
        columns = [gains.terms(zero, list(e), zero) for e in np.eye(N)]
        Kp = np.array([[c[i][0] for c in columns] for i in range(N)])
        Ki = np.array([[c[i][1] for c in columns] for i in range(N)])
        rates = [gains.terms(zero, zero, list(r)) for r in np.eye(N)]
        Kd = np.array([[c[i][2] for c in rates] for i in range(N)])
    per_angle = 1.0 / MODEL.length
    # state: arm (3N), the command pending (N), the integral (N); the reference is 0
    closed = np.zeros((5 * N, 5 * N))
    closed[: 3 * N, : 3 * N] = F
    closed[: 3 * N, 3 * N : 4 * N] = G
    closed[4 * N :, 4 * N :] = np.eye(N)
    closed[4 * N :, :N] = -Ki * PERIOD * per_angle
    closed[3 * N : 4 * N, :N] = -(Kp + Ki * PERIOD) * per_angle
    closed[3 * N : 4 * N, N : 2 * N] = -Kd * per_angle
    closed[3 * N : 4 * N, 4 * N :] = np.eye(N)
    return np.log(np.linalg.eigvals(closed).astype(complex)) / PERIOD


def test_the_per_segment_pi_leaves_the_six_segment_arms_first_mode_growing() -> None:
    poles = closed_loop_poles(None)
    assert max(poles.real) > 0.5  # 0.7 1/s: the base's mode, under-damped and under-phased


@pytest.mark.parametrize("mass_scale", [1.0, 0.6, 1.3])
def test_the_arm_loops_damp_every_mode_of_the_six_segment_arm(mass_scale: float) -> None:
    """Designed on the arm's M and run on M 40 % lighter or 30 % heavier (a curled arm, an
    estimate off): every pole damped at zeta >= 0.55, the slowest decaying at >= 1.5 1/s."""
    gains = arm_loop_gains([MODEL] * N, [MASS] * N, 0.015, max_crossover_hz=1.0)
    poles = closed_loop_poles(gains, mass_scale)
    moving = poles[np.abs(poles) > 1e-9]
    assert min(-moving.real / np.abs(moving)) >= 0.55
    assert max(poles.real) <= -1.5


def test_without_inertia_the_arm_loops_are_the_per_segment_pi() -> None:
    """M -> 0: the proportional and integral terms are Kp e and Ki e of `outer_loop_gains`
    (Kp = wc tau / K, Ki = Kp / tau), no coupling, no damping term."""
    gains = arm_loop_gains([MODEL] * N, [1e-15] * N, 0.015, max_crossover_hz=1.0)
    pi = outer_loop_gains(MODEL, 0.015, max_crossover_hz=1.0)
    errors = [0.5, -1.0, 2.0, 0.0, -0.3, 1.5]
    terms = gains.terms([3.0] * N, errors, [4.0] * N)
    for (proportional, integral, damping), e in zip(terms, errors, strict=True):
        assert proportional == pytest.approx(pi.Kp * e, rel=1e-9, abs=1e-15)
        assert integral == pytest.approx(pi.Ki * e, rel=1e-9, abs=1e-15)
        assert abs(damping) < 1e-12


def test_the_loops_feed_the_inverse_dynamics_forward_on_a_move() -> None:
    """On a planned move the feedforward is T^-1 ((D + 3 p M) rate + M acceleration) L: the
    base's piston answers the outer segments' acceleration through M's off-diagonal terms."""
    gains = arm_loop_gains([MODEL] * N, [MASS] * N, 0.015, max_crossover_hz=1.0)
    zero = [0.0] * N
    accelerate = [0.0, 10.0, 0.0, 0.0, 0.0, 0.0]
    at_rest = gains.terms(zero, zero, zero, (zero, zero))
    moving = gains.terms(zero, zero, zero, (zero, accelerate))
    M = mass_matrix(zero, [MODEL.length] * N, [MASS] * N)
    torque = MODEL.static_gain() * MODEL.length * (MODEL.k_bend + MODEL.gas_stiffness())
    expected = M[0, 1] * 10.0 * MODEL.length / torque
    assert moving[0][0] - at_rest[0][0] == pytest.approx(expected, rel=1e-12)
    assert expected > 0.0


def test_coupled_bends_of_one_segment_are_the_bend_discretiser() -> None:
    """One bend: the coupled discretisation (Van Loan over halved steps, then doubled) equals
    the per-bend one to rounding, F, G and Q."""
    bend = BendModel(0.06, 5.4e-6, 0.025, 6e-3, 7.7e-7)
    coupled = CoupledBends([bend], np.array([[5.4e-6]]), [1e-8])(0.01)
    single = BendDiscretiser(bend, 1e-8)(0.01)
    for got, want in zip(coupled, single, strict=True):
        assert np.allclose(
            np.ravel(got), np.ravel(want), rtol=1e-9, atol=1e-14 * np.abs(want).max()
        )


def test_coupled_bends_of_the_six_segment_arm_are_finite_and_positive() -> None:
    """The six-segment arm's fastest mode (|lambda| ~ 1e4 1/s) over a 10 ms step: F's spectral
    radius below 1, Q symmetric positive definite (one Van Loan step would cancel every digit)."""
    lengths, masses = [0.06] * N, [MASS] * N
    bends = [BendModel(0.06, 0.0, 0.025, 6e-3, 7.7e-7)] * N
    F, G, Q = CoupledBends(bends, mass_matrix([0.0] * N, lengths, masses), [1e-8] * N)(0.01)
    assert max(abs(np.linalg.eigvals(F))) < 1.0
    assert np.allclose(Q, Q.T) and min(np.linalg.eigvalsh(Q)) > 0.0
    assert np.all(np.isfinite(G))


def test_the_ukf_predicts_a_curled_arm_with_its_own_mass_matrix() -> None:
    """Held curled in front of the camera, the whole-arm UKF of a multibody arm rediscretises
    its prediction with the mass matrix at its estimate: the base's entry a third of the
    straight arm's, equal to `mass_matrix` at the estimated curvatures to the 2 % it allows."""
    from controllers.estimation import CameraNoise, MarkerFrame
    from controllers.estimators import make_estimator
    from controllers.kinematics import markers

    lengths, masses = [MODEL.length] * N, [MASS] * N
    curled = np.array([-11.9, -16.0, -16.2, -12.2, -7.0, -2.2])
    bends = [BendModel(MODEL.length, 1e-3, MODEL.k_bend, MODEL.d_bend, MODEL.G_a)] * N
    estimator = make_estimator(
        "ukf",
        bends,
        (0.0, 0.0, 0.0),
        CameraNoise(noise=1e-4),
        PERIOD,
        torque_std=0.05,
        masses=masses,
    )
    points = markers(curled, lengths, (0.0, 0.0, 0.0))
    for cycle in range(1, 60):
        estimate = estimator.update(cycle * PERIOD, {}, [MarkerFrame((cycle - 1) * PERIOD, points)])
    assert estimate.kappa == pytest.approx(curled, abs=0.2)
    scheduled = estimator._scheduled  # type: ignore[attr-defined]
    straight = mass_matrix([0.0] * N, lengths, masses)
    assert scheduled[0, 0] < 0.4 * straight[0, 0]
    here = mass_matrix(estimate.kappa, lengths, masses)
    assert np.max(np.abs(scheduled - here)) <= 0.02 * np.max(np.abs(scheduled))


def test_a_planned_move_feeds_the_inverse_dynamics_to_the_pistons() -> None:
    """The planar controller on the body: the same cycle with and without a planned move's
    rate and acceleration differs, segment by segment, by the arm loops' feedforward."""
    from pathlib import Path

    from controllers.estimation import Estimate
    from hil.scenario import load_scenario
    from rigbus.protocol import DriveCommand, Protocol
    from robots.planar_arm.controller.curvature_control import CurvatureControl
    from robots.planar_arm.plant.rig import ROBOT

    scenario = load_scenario(
        Path(__file__).parents[1] / "robots/planar_arm/scenarios/planar-point-to-point.toml"
    )
    config = ROBOT.controller_config(scenario)
    gains = config.arm_gains
    assert gains is not None
    zero = np.zeros(N)
    estimate = Estimate(zero, zero, zero)
    motion = (np.array([1.0, -2.0, 0.5, 0.0, 3.0, -1.0]), np.array([5.0, 0.0, -4.0, 2.0, 0.0, 1.0]))

    def pistons(with_motion: bool) -> list[float]:
        control = CurvatureControl(config, Protocol())
        frames = control.command(0, zero, estimate, {}, motion if with_motion else None)
        return [f.piston_setpoint for f in frames if isinstance(f, DriveCommand)]

    moved, still = pistons(True), pistons(False)
    forward = [
        a[0] - b[0]
        for a, b in zip(
            gains.terms(zero, zero, zero, motion), gains.terms(zero, zero, zero), strict=True
        )
    ]
    assert np.subtract(moved, still) == pytest.approx(forward, rel=1e-9, abs=1e-12)
    assert max(abs(v) for v in forward) > 1e-4  # a tenth of a millimetre and more
