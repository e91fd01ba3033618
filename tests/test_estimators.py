"""Tests for the curvature estimators (controllers.estimators: raw, kf, ukf) on a synthetic arm
(tests/synthetic_arm.py: the bend ODE integrated exactly, the camera of hil.vision, no FMUs).

Laws checked: the filters track a step and sines and beat the geometric inversion by at least 2x
in RMS at 0.5 mm marker noise; they coast through dropouts and occlusions with an honest standard
deviation and recover; the gate rejects outliers and no estimate strays beyond 5 of its own
standard deviations; latency compensation lowers the error; the normalised innovation squared
(NIS) sits in its chi-square 95 % band; reruns are bit-identical.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from scipy.stats import chi2
from synthetic_arm import BASE, SEGMENT, Run, T, camera_noise, simulate

from controllers.bend_filter import _pressure_inputs, unmodelled_torque_std
from controllers.estimation import DriveReading, MarkerFrame
from controllers.estimators import OfflineEstimates, make_estimator, run_offline
from controllers.fast_linalg import inverse, robust_sqrt
from controllers.kinematics import markers
from hil.vision import CameraEffects

SEGMENTS = 3
DEFAULT = CameraEffects(noise=5e-4, dropout=0.01, outlier_rate=0.001, outlier_distance=0.02)
SETTLE = 30  # cycles before errors count: the filters start from the straight arm, P at the limit
# how many of its own standard deviations an error may reach: 5 where the filter's variance is
# consistent; kf's segments 2 and 3 are over-confident by about 1.4x (their start heading comes
# from the other segments' filters, whose errors they are correlated with and do not know), so
# their bound is 7: a documented limitation of per-segment filters, not a tuning
SIGMAS = {"kf": np.array([5.0, 7.0, 7.0]), "ukf": np.full(3, 5.0)}


def pressure(t: float) -> np.ndarray:
    """A sine on segment 1, a step on segment 2, a faster sine on segment 3 [Pa]."""
    return np.array(
        [
            20000.0 * np.sin(2.0 * np.pi * 0.5 * t),
            15000.0 * (t >= 0.5),
            -20000.0 * np.sin(2.0 * np.pi * 1.3 * t),
        ]
    )


@functools.cache
def synthetic(effects: CameraEffects, cycles: int, seed: int) -> Run:
    return simulate(
        pressure, effects, cycles, seed, SEGMENTS, torque_std=unmodelled_torque_std(SEGMENT)
    )


@functools.cache
def estimate(
    name: str, effects: CameraEffects, cycles: int, seed: int, compensate: bool = True
) -> OfflineEstimates:
    estimator = make_estimator(
        name, [SEGMENT] * SEGMENTS, BASE, camera_noise(effects), T, compensate
    )
    return run_offline(estimator, synthetic(effects, cycles, seed).cycles)


def rms(name: str, effects: CameraEffects, cycles: int, seed: int, compensate: bool = True):
    """RMS curvature error per segment after settling [1/m], shape (N,)."""
    error = (
        estimate(name, effects, cycles, seed, compensate).kappa
        - synthetic(effects, cycles, seed).kappa
    )
    return np.sqrt((error[SETTLE:] ** 2).mean(axis=0))


@pytest.mark.parametrize("name", ["raw", "kf", "ukf"])
def test_each_estimator_tracks_a_step_and_sines(name: str) -> None:
    """At 0.05 mm marker noise (raw amplifies noise along the chain: at 0.5 mm its tip segment
    is mostly noise) every estimator follows the arm within 10 % of its motion."""
    low = CameraEffects(noise=5e-5)
    truth = synthetic(low, 400, 1).kappa[SETTLE:]
    spread = np.sqrt((truth**2).mean(axis=0))
    assert (spread > 2.0).all()  # the arm really moves: several 1/m on every segment
    assert (rms(name, low, 400, 1) < 0.1 * spread).all()
    # after the step on segment 2 the estimate settles at the static bend G_a dp / (k L)
    static = SEGMENT.G_a * 15000.0 / (SEGMENT.k_bend * SEGMENT.length)
    final = estimate(name, low, 400, 1).kappa[-50:, 1].mean()
    assert abs(final - static) < 0.05 * static


@pytest.mark.parametrize("name", ["kf", "ukf"])
def test_filters_at_least_halve_the_raw_error_at_half_a_millimetre(name: str) -> None:
    raw = np.sqrt((rms("raw", DEFAULT, 600, 1) ** 2).mean())
    assert np.sqrt((rms(name, DEFAULT, 600, 1) ** 2).mean()) <= 0.5 * raw


@pytest.mark.parametrize("name", ["kf", "ukf"])
def test_latency_compensation_lowers_the_error(name: str) -> None:
    on, off = rms(name, DEFAULT, 600, 1, True), rms(name, DEFAULT, 600, 1, False)
    assert np.sqrt((on**2).mean()) < np.sqrt((off**2).mean())
    # kf's segment 1 (start heading the known base) and ukf's whole arm gain at least 10 %:
    # a frame is one control period old, and segment 1 moves fastest
    if name == "kf":
        assert on[0] < 0.9 * off[0]
    else:
        assert np.sqrt((on**2).mean()) < 0.9 * np.sqrt((off**2).mean())


@pytest.mark.parametrize("name", ["kf", "ukf"])
def test_filters_coast_through_dropouts_and_occlusions_and_recover(name: str) -> None:
    effects = CameraEffects(noise=5e-4, dropout=0.2, occlusion_interval=2.0, occlusion_duration=0.2)
    run = synthetic(effects, 800, 2)
    result = estimate(name, effects, 800, 2)
    blind = result.measured == 0
    # find the occlusions: streaks of at least 10 cycles without a measurement
    streaks, start = [], None
    for c in range(SETTLE, len(blind)):
        if blind[c] and start is None:
            start = c
        elif not blind[c] and start is not None:
            if c - start >= 10:
                streaks.append((start, c))
            start = None
    assert streaks, "the seed must produce at least one occlusion"
    error = np.abs(result.kappa - run.kappa)
    std = result.kappa_std
    for begin, end in streaks:
        # coasting: the uncertainty grows and the error stays within it
        assert (np.diff(std[begin:end], axis=0) > 0.0).all()
        assert (error[begin:end] < SIGMAS[name] * std[begin:end]).all()
        if not any(begin_next <= end + 20 for begin_next, _ in streaks if begin_next > begin):
            # recovered within 0.2 s: the uncertainty is back near its level before the burst
            assert (std[end + 20] < 1.5 * std[begin - 1]).all()
    assert (error[SETTLE:] < SIGMAS[name] * std[SETTLE:]).all()
    assert np.sqrt((error[SETTLE:] ** 2).mean()) < 0.1 * np.sqrt((run.kappa**2).mean())


@pytest.mark.parametrize("name", ["kf", "ukf"])
def test_outliers_are_gated_and_never_move_an_estimate_far(name: str) -> None:
    effects = CameraEffects(noise=5e-4, outlier_rate=0.01, outlier_distance=0.02)
    run = synthetic(effects, 800, 3)
    result = estimate(name, effects, 800, 3)
    error = result.kappa - run.kappa
    std = result.kappa_std
    assert (np.abs(error[SETTLE:]) < SIGMAS[name] * std[SETTLE:]).all()
    # an update moves each estimate by less than 5 of its previous standard deviations beyond
    # what the arm itself did
    jump = np.abs(np.diff(result.kappa, axis=0) - np.diff(run.kappa, axis=0))
    assert (jump[SETTLE:] < SIGMAS[name] * std[SETTLE:-1]).all()
    # kf: an outlier on marker i spoils the chords of segments i and i + 1; ukf ignores the base
    # marker and tests every other marker once
    if name == "kf":
        spoiled = run.outliers[0] + 2 * run.outliers[1:-1].sum() + run.outliers[-1]
    else:
        spoiled = run.outliers[1:].sum()
    assert spoiled > 20
    assert result.gated.sum() >= 0.8 * spoiled
    # and the gate seldom rejects a good measurement (0.1 % by design)
    assert result.gated.sum() <= spoiled + 0.005 * result.measured.sum()


def test_nis_within_the_chi_square_band_over_a_long_run() -> None:
    """Normalised innovation squared: its sum over n scalar degrees of freedom is chi-square with
    n dof when the filter's noise models are right. kf: segment 1, whose start heading is the
    known base (distal segments see correlated heading errors the per-segment filters ignore);
    ukf: every marker update."""
    effects = CameraEffects(noise=5e-4)
    run = synthetic(effects, 800, 4)
    for name in ("kf", "ukf"):
        estimator = make_estimator(name, [SEGMENT] * SEGMENTS, BASE, camera_noise(effects), T)
        total, dof, gated, measured = 0.0, 0, 0, 0
        for c, (t, drives, frames) in enumerate(run.cycles):
            estimate_ = estimator.update(t, drives, frames)
            gated += estimate_.gated
            measured += estimate_.measured + estimate_.gated
            if c < SETTLE or estimate_.measured == 0:
                continue
            y = estimator.innovation
            S = estimator.innovation_covariance
            if name == "kf":
                if estimate_.measured != SEGMENTS:
                    continue
                y, S = y[:1], S[:1, :1]
            total += float(y @ np.linalg.solve(S, y))
            dof += len(y)
        low, high = chi2.ppf([0.025, 0.975], dof) / dof
        assert low < total / dof < high, (name, total / dof, low, high)
        # without outliers the gate rejects a good measurement with probability 0.001
        expected = 0.001 * measured
        assert gated <= expected + 3.0 * np.sqrt(expected) + 1.0, (name, gated, measured)


@pytest.mark.parametrize("name", ["raw", "kf", "ukf"])
def test_same_inputs_give_bit_identical_estimates(name: str) -> None:
    effects = CameraEffects(noise=5e-4, dropout=0.1, outlier_rate=0.01, outlier_distance=0.02)
    first = estimate(name, effects, 300, 5)
    again = run_offline(
        make_estimator(name, [SEGMENT] * SEGMENTS, BASE, camera_noise(effects), T),
        synthetic(effects, 300, 5).cycles,
    )
    for a, b in zip(
        (first.kappa, first.kappa_std, first.gated, first.measured),
        (again.kappa, again.kappa_std, again.gated, again.measured),
        strict=True,
    ):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", ["kf", "ukf"])
def test_partial_frames_update_what_they_can(name: str) -> None:
    """Markers 0 and 1 missing: kf updates segment 3 (its markers 2 and 3 are seen) with the
    heading from its own estimate of segments 1 and 2, ukf uses markers 2 and 3."""
    kappas = np.array([3.0, -2.0, 4.0])
    points = markers(kappas, [SEGMENT.length] * SEGMENTS, BASE)
    points[:2] = np.nan
    estimator = make_estimator(
        name, [SEGMENT] * SEGMENTS, BASE, camera_noise(CameraEffects(noise=5e-4)), T
    )
    drives = {n: DriveReading(0.025, 0.0, 0.0) for n in (1, 2, 3)}
    estimator.update(0.0, drives, [])
    result = estimator.update(T, drives, [MarkerFrame(0.0, points)])
    assert result.measured == (1 if name == "kf" else 2)
    assert result.gated == 0


def test_raw_inverts_complete_frames_and_holds_otherwise() -> None:
    kappas = np.array([3.0, -2.0, 4.0])
    points = markers(kappas, [SEGMENT.length] * SEGMENTS, BASE)
    raw = make_estimator("raw", [SEGMENT] * SEGMENTS, BASE, camera_noise(DEFAULT), T)
    first = raw.update(T, {}, [MarkerFrame(0.0, points)])
    np.testing.assert_allclose(first.kappa, kappas, rtol=1e-12)
    assert np.isnan(first.kappa_std).all()
    partial = points.copy()
    partial[2] = np.nan
    held = raw.update(2 * T, {}, [MarkerFrame(T, partial)])
    np.testing.assert_array_equal(held.kappa, first.kappa)
    assert held.measured == 0
    moved = markers(kappas + 1.0, [SEGMENT.length] * SEGMENTS, BASE)
    rate = raw.update(3 * T, {}, [MarkerFrame(2 * T, moved)]).kappa_rate
    np.testing.assert_allclose(rate, 1.0 / (2 * T), rtol=1e-9)


def test_unknown_estimator_is_named() -> None:
    with pytest.raises(ValueError, match="unknown estimator 'ekf'"):
        make_estimator("ekf", [SEGMENT], BASE, camera_noise(DEFAULT), T)


@pytest.mark.parametrize("name", ["kf", "ukf"])
def test_a_late_frame_gives_the_estimate_of_a_frame_fused_on_time(name: str) -> None:
    """Latency compensation is exact: frames fused late (at the SYNC after they became
    available) leave the same estimate as an estimator that was called at each exposure time
    itself, with the drive readings then in force, and given the frame there. Exposures jitter
    between SYNCs; estimates are compared at the SYNCs where both have seen the same frames."""
    effects = CameraEffects(noise=5e-4, dropout=0.1, jitter=3e-3)
    run = synthetic(effects, 150, 6)
    frames_all = sorted(
        (f for _, _, frames in run.cycles for f in frames), key=lambda f: f.exposure_time
    )
    late = make_estimator(name, [SEGMENT] * SEGMENTS, BASE, camera_noise(effects), T)
    on_time = make_estimator(name, [SEGMENT] * SEGMENTS, BASE, camera_noise(effects), T)
    previous: dict[int, DriveReading] = {}
    fused_late: set[float] = set()
    fused_on_time: set[float] = set()
    compared = between = 0
    for t, drives, frames in run.cycles:
        while frames_all and frames_all[0].exposure_time < t - 1e-9:
            frame = frames_all.pop(0)
            between += frame.exposure_time > t - T + 1e-9
            on_time.update(frame.exposure_time, previous, [frame])
            fused_on_time.add(frame.exposure_time)
        expected = on_time.update(t, drives, [])
        result = late.update(t, drives, frames)
        fused_late.update(f.exposure_time for f in frames)
        previous = drives
        if fused_late == fused_on_time:
            np.testing.assert_allclose(result.kappa, expected.kappa, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(result.kappa_std, expected.kappa_std, rtol=1e-9)
            compared += 1
    assert between > 50 and compared > 100


def test_inverse_and_square_root_are_numpys_bit_for_bit() -> None:
    """The UKF's inverse and Cholesky factor call numpy's kernels without np.linalg's wrapping:
    the same bits on covariances of the UKF's sizes, np.linalg.inv's error on a singular
    matrix, and the eigen square root where Cholesky fails (an indefinite matrix)."""
    rng = np.random.default_rng(5)
    for n in (2, 4, 12, 24):
        for _ in range(20):
            A = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-6, 2)
            S = A @ A.T + 1e-9 * np.eye(n)
            assert np.array_equal(inverse(S), np.linalg.inv(S))
            assert np.array_equal(inverse(A), np.linalg.inv(A))
            assert np.array_equal(robust_sqrt(S), np.linalg.cholesky(S).T)
    with pytest.raises(np.linalg.LinAlgError):
        inverse(np.ones((3, 3)))
    P = np.diag([1.0, 4.0, -1e-12])  # indefinite by rounding: the positive part's square root
    U = robust_sqrt(P)
    assert np.allclose(U.T @ U, np.diag([1.0, 4.0, 0.0]))
    assert np.isfinite(U).all()


def test_pressure_inputs_keep_a_missing_drives_last_value() -> None:
    """h(p_a) - h(p_b) per segment from the drives heard this cycle; a drive not heard keeps its
    last value (zero before its first), and the last inputs are not changed in place."""
    import dataclasses

    bends = [SEGMENT, dataclasses.replace(SEGMENT, vacuum_factor=0.5, p_collapse=5e3), SEGMENT]
    first = _pressure_inputs({2: DriveReading(0.02, 3e4, -2e4)}, None, bends)
    expected = 3e4 - bends[1].effective_pressure(-2e4)
    assert first.tolist() == [0.0, expected, 0.0] and expected != 5e4  # the collapse counts
    second = _pressure_inputs({1: DriveReading(0.02, 1e4, 0.0)}, first, bends)
    assert second.tolist() == [1e4, expected, 0.0]
    assert first.tolist() == [0.0, expected, 0.0] and second.dtype == np.float64
