"""Tests for controllers.kinematics: planar piecewise-constant-curvature arcs and their inverse.

The oracle for positions is the chord form of a circular arc, written independently here: the
chord has length L sinc(k L / 2) and points along the mean of the start and end headings. Unlike
(sin(th0 + k L) - sin th0) / k it has no cancellation for small k L.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from controllers.kinematics import (
    SMALL_CURVATURE,
    SMALL_HALF_ANGLE,
    backbone,
    curvatures_from_markers,
    forward,
    markers,
    point_jacobian,
    pose_at,
    segment_end,
    tip_hessian,
    tip_jacobian,
)

LENGTH = 0.06  # [m] a segment of the planar arm
KAPPA_MAX = 1.6 / LENGTH  # [1/m] theta_max / L
HEADINGS = (0.0, 0.3, 1.0, math.pi / 2, 2.5, -2.0, math.pi)


def chord_end(pose: tuple[float, float, float], kappa: float, length: float) -> tuple[float, float]:
    """End point of an arc by its chord: length L sin(k L/2) / (k L/2), direction th0 + k L/2."""
    x0, y0, th0 = pose
    half = 0.5 * kappa * length
    chord = length if half == 0.0 else length * math.sin(half) / half
    return x0 + chord * math.cos(th0 + half), y0 + chord * math.sin(th0 + half)


@pytest.mark.parametrize("heading", HEADINGS)
def test_straight_segment_ends_length_along_the_heading(heading: float) -> None:
    x, y, th = segment_end((0.2, -0.1, heading), 0.0, LENGTH)
    assert x == pytest.approx(0.2 + LENGTH * math.cos(heading), abs=1e-15)
    assert y == pytest.approx(-0.1 + LENGTH * math.sin(heading), abs=1e-15)
    assert th == heading


@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("heading", [0.0, math.pi / 2])
def test_quarter_circle_ends_at_the_known_point(sign: float, heading: float) -> None:
    # kappa L = +-pi/2: radius R = 1/|kappa|; from heading th0 the end is R along the heading and
    # R to the side of the centre (left for kappa > 0), and the heading has turned by +-pi/2.
    kappa = sign * math.pi / (2.0 * LENGTH)
    radius = 1.0 / abs(kappa)
    x, y, th = segment_end((0.0, 0.0, heading), kappa, LENGTH)
    forward_dir = (math.cos(heading), math.sin(heading))
    left = (-math.sin(heading), math.cos(heading))
    expected = (
        radius * forward_dir[0] + sign * radius * left[0],
        radius * forward_dir[1] + sign * radius * left[1],
    )
    assert (x, y) == pytest.approx(expected, abs=1e-15)
    assert th == pytest.approx(heading + sign * math.pi / 2, abs=1e-15)


def test_quarter_circle_in_numbers() -> None:
    # L = 0.06, kappa = pi / 0.12: R = 0.12 / pi = 0.0381971863...
    x, y, th = segment_end((0.0, 0.0, 0.0), math.pi / 0.12, 0.06)
    assert x == pytest.approx(0.12 / math.pi, rel=1e-14)
    assert y == pytest.approx(0.12 / math.pi, rel=1e-14)
    assert th == pytest.approx(math.pi / 2, rel=1e-15)


def test_full_circle_returns_to_the_base() -> None:
    x, y, th = segment_end((0.1, 0.2, 0.7), 2.0 * math.pi / LENGTH, LENGTH)
    assert (x, y) == pytest.approx((0.1, 0.2), abs=1e-15)
    assert th == pytest.approx(0.7 + 2.0 * math.pi, rel=1e-15)


@pytest.mark.parametrize("heading", HEADINGS)
@pytest.mark.parametrize("kappa", [0.0, 3e-7, -0.9e-6, 0.9e-6, math.nextafter(SMALL_CURVATURE, 0)])
def test_small_curvature_series_matches_the_arc(heading: float, kappa: float) -> None:
    x, y, _ = segment_end((0.0, 0.0, heading), kappa, LENGTH)
    xc, yc = chord_end((0.0, 0.0, heading), kappa, LENGTH)
    assert abs(x - xc) <= 1e-12 * LENGTH
    assert abs(y - yc) <= 1e-12 * LENGTH


@pytest.mark.parametrize("heading", HEADINGS)
@pytest.mark.parametrize("kappa", [1e-2, -0.5, 7.0, -26.0])
def test_exact_formula_matches_the_arc_at_ordinary_curvatures(heading: float, kappa: float) -> None:
    x, y, _ = segment_end((0.0, 0.0, heading), kappa, LENGTH)
    xc, yc = chord_end((0.0, 0.0, heading), kappa, LENGTH)
    assert abs(x - xc) <= 1e-12 * LENGTH
    assert abs(y - yc) <= 1e-12 * LENGTH


def test_series_branch_is_continuous_with_the_exact_formula() -> None:
    below, above = 0.9e-6, 1.1e-6
    for heading in HEADINGS:
        for kappa in (below, above, -below, -above):
            x, y, _ = segment_end((0.0, 0.0, heading), kappa, LENGTH)
            xc, yc = chord_end((0.0, 0.0, heading), kappa, LENGTH)
            assert abs(x - xc) <= 1e-12 * LENGTH, (heading, kappa)
            assert abs(y - yc) <= 1e-12 * LENGTH, (heading, kappa)
        # the two one-sided limits at the threshold agree
        left = segment_end((0.0, 0.0, heading), math.nextafter(SMALL_CURVATURE, 0.0), LENGTH)
        right = segment_end((0.0, 0.0, heading), SMALL_CURVATURE, LENGTH)
        assert left == pytest.approx(right, rel=1e-12, abs=1e-12 * LENGTH), heading


@pytest.mark.parametrize("n", range(1, 7))
@pytest.mark.parametrize("base_heading", [math.pi / 2, 0.0, -1.2, 3.0])
def test_forward_then_inverse_round_trips(n: int, base_heading: float) -> None:
    rng = np.random.default_rng(1000 * n + round(100 * base_heading))
    lengths = rng.uniform(0.04, 0.08, n).tolist()
    for _ in range(20):
        kappas = rng.uniform(-KAPPA_MAX, KAPPA_MAX, n).tolist()
        points = markers(kappas, lengths, (0.01, -0.02, base_heading))
        recovered = curvatures_from_markers(points, lengths, base_heading)
        assert recovered.shape == (n,)
        np.testing.assert_allclose(recovered, kappas, rtol=0.0, atol=1e-9)


def test_round_trip_of_a_straight_and_a_negative_arm() -> None:
    lengths = [LENGTH] * 4
    for kappas in ([0.0, 0.0, 0.0, 0.0], [-26.0, -1.0, -13.5, -0.25], [0.0, -20.0, 0.0, 20.0]):
        points = markers(kappas, lengths, (0.0, 0.0, math.pi / 2))
        recovered = curvatures_from_markers(points, lengths, math.pi / 2)
        np.testing.assert_allclose(recovered, kappas, rtol=0.0, atol=1e-9)


def test_round_trip_across_the_heading_wrap() -> None:
    # base heading near pi and bends on both sides: chord angles cross +-pi
    lengths = [LENGTH] * 3
    kappas = [20.0, -25.0, 15.0]
    for base_heading in (math.pi - 0.1, -math.pi + 0.1, math.pi):
        points = markers(kappas, lengths, (0.0, 0.0, base_heading))
        recovered = curvatures_from_markers(points, lengths, base_heading)
        np.testing.assert_allclose(recovered, kappas, rtol=0.0, atol=1e-9)


def test_round_trip_of_near_zero_curvatures() -> None:
    lengths = [LENGTH] * 3
    kappas = [1.1e-6, 2e-6, -1.5e-6]
    points = markers(kappas, lengths, (0.0, 0.0, math.pi / 2))
    recovered = curvatures_from_markers(points, lengths, math.pi / 2)
    np.testing.assert_allclose(recovered, kappas, rtol=0.0, atol=1e-9)


def test_heading_accumulates_kappa_times_length() -> None:
    rng = np.random.default_rng(7)
    kappas = rng.uniform(-KAPPA_MAX, KAPPA_MAX, 5)
    lengths = rng.uniform(0.04, 0.08, 5)
    poses = forward(kappas.tolist(), lengths.tolist(), (0.0, 0.0, 0.4))
    expected = 0.4 + np.concatenate(([0.0], np.cumsum(kappas * lengths)))
    np.testing.assert_allclose(poses[:, 2], expected, rtol=0.0, atol=1e-14)


@pytest.mark.parametrize("n", [0, 1, 3, 6])
def test_marker_count_is_segments_plus_one(n: int) -> None:
    base = (0.05, -0.03, math.pi / 2)
    kappas, lengths = [5.0] * n, [LENGTH] * n
    poses = forward(kappas, lengths, base)
    points = markers(kappas, lengths, base)
    assert poses.shape == (n + 1, 3)
    assert points.shape == (n + 1, 2)
    assert tuple(poses[0]) == base
    np.testing.assert_array_equal(points, poses[:, :2])


def test_markers_of_a_chain_follow_segment_by_segment() -> None:
    kappas, lengths = [10.0, -5.0], [0.05, 0.07]
    poses = forward(kappas, lengths, (0.0, 0.0, math.pi / 2))
    first = segment_end((0.0, 0.0, math.pi / 2), 10.0, 0.05)
    second = segment_end(first, -5.0, 0.07)
    np.testing.assert_array_equal(poses, np.array([(0.0, 0.0, math.pi / 2), first, second]))


def test_mismatched_lengths_are_rejected() -> None:
    with pytest.raises(ValueError):
        forward([1.0, 2.0], [LENGTH], (0.0, 0.0, 0.0))


# ---------------------------------------------------------------- along the arm, and Jacobians


def random_arm(rng: np.random.Generator, n: int, near_zero: bool = False) -> tuple:
    """Seeded lengths, curvatures (mixed signs; near zero or exactly zero if asked) and base."""
    lengths = rng.uniform(0.04, 0.08, n)
    if near_zero:
        kappas = rng.choice([0.0, 1.0], n) * rng.uniform(-1e-3, 1e-3, n)
    else:
        kappas = rng.uniform(-KAPPA_MAX, KAPPA_MAX, n)
    return kappas, lengths, (0.03, -0.01, float(rng.uniform(-math.pi, math.pi)))


def central_difference(f, kappas: np.ndarray, h: float = 1e-5) -> np.ndarray:
    columns = []
    for i in range(len(kappas)):
        up, down = kappas.copy(), kappas.copy()
        up[i] += h
        down[i] -= h
        columns.append((np.asarray(f(up)) - np.asarray(f(down))) / (2.0 * h))
    return np.stack(columns, axis=-1)


@pytest.mark.parametrize("n", [1, 2, 6])
def test_pose_at_every_joint_is_the_forward_pose(n: int) -> None:
    kappas, lengths, base = random_arm(np.random.default_rng(n), n)
    poses = forward(kappas, lengths, base)
    joints = np.concatenate(([0.0], np.cumsum(lengths)))
    for i, s in enumerate(joints):
        np.testing.assert_array_equal(pose_at(kappas, lengths, base, float(s)), poses[i])


def test_pose_inside_a_segment_lies_on_its_circle() -> None:
    # segment 1 of a 3-segment arm: every point is 1/|k| from the circle's centre and its
    # heading has turned by k times the arc length travelled
    kappas, lengths, base = [12.0, -20.0, 5.0], [0.05, 0.06, 0.07], (0.0, 0.0, 0.4)
    x0, y0, th0 = forward(kappas, lengths, base)[1]
    centre = (x0 - math.sin(th0) / -20.0, y0 + math.cos(th0) / -20.0)
    for partial in (1e-4, 0.02, 0.0599):
        x, y, th = pose_at(kappas, lengths, base, 0.05 + partial)
        assert math.hypot(x - centre[0], y - centre[1]) == pytest.approx(1 / 20.0, rel=1e-12)
        assert th == pytest.approx(th0 - 20.0 * partial, abs=1e-14)


@pytest.mark.parametrize("s", [-1e-3, 0.18 + 1e-3, math.inf, math.nan])
def test_pose_beyond_the_arm_is_an_error_naming_s(s: float) -> None:
    with pytest.raises(ValueError, match="arc length s = "):
        pose_at([1.0, 2.0, 3.0], [0.06] * 3, (0.0, 0.0, 0.0), s)


def test_rounding_sized_arc_lengths_snap_to_the_ends() -> None:
    kappas, lengths, base = [7.0, -3.0, 11.0], [0.1, 0.2, 0.3], (0.0, 0.0, 1.0)
    total = 0.1 + 0.2 + 0.3  # 0.6000000000000001 in this order, not fsum's 0.6
    np.testing.assert_array_equal(
        pose_at(kappas, lengths, base, total), forward(kappas, lengths, base)[-1]
    )


def test_backbone_samples_the_arcs_evenly_and_hits_the_joints() -> None:
    kappas, lengths, base = [15.0, 0.0, -25.0], [0.05, 0.06, 0.07], (0.1, 0.0, 2.0)
    rows = backbone(kappas, lengths, base, per_segment=5)
    assert rows.shape == (16, 3)
    np.testing.assert_array_equal(rows[::5], forward(kappas, lengths, base))
    # consecutive samples: a chord of an arc of L/5, heading turned by k L/5
    for i, (kappa, length) in enumerate(zip(kappas, lengths, strict=True)):
        step = length / 5
        for j in range(5):
            a, b = rows[5 * i + j], rows[5 * i + j + 1]
            chord = step if kappa == 0.0 else 2 * math.sin(kappa * step / 2) / kappa
            assert math.hypot(*(b[:2] - a[:2])) == pytest.approx(abs(chord), rel=1e-12)
            assert b[2] - a[2] == pytest.approx(kappa * step, abs=1e-14)
    with pytest.raises(ValueError, match="per_segment"):
        backbone(kappas, lengths, base, per_segment=0)


@pytest.mark.parametrize("near_zero", [False, True])
@pytest.mark.parametrize("n", [1, 3, 6])
def test_tip_jacobian_matches_central_differences(n: int, near_zero: bool) -> None:
    rng = np.random.default_rng(10 * n + near_zero)
    for _ in range(10):
        kappas, lengths, base = random_arm(rng, n, near_zero)
        jacobian = tip_jacobian(kappas, lengths, base)
        numeric = central_difference(
            lambda k, lengths=lengths, base=base: forward(k, lengths, base)[-1], kappas
        )
        # central differences err by h^2 |d3 tip| ~ 1e-10 L^4 |...|, far below this
        np.testing.assert_allclose(jacobian, numeric, rtol=0.0, atol=1e-9)


def test_point_jacobian_matches_central_differences_along_the_arm() -> None:
    rng = np.random.default_rng(5)
    for near_zero in (False, True):
        kappas, lengths, base = random_arm(rng, 4, near_zero)
        for s in (0.0, float(lengths[0]), *rng.uniform(0.0, lengths.sum(), 5), lengths.sum()):
            jacobian = point_jacobian(kappas, lengths, base, float(s))
            numeric = central_difference(
                lambda k, lengths=lengths, base=base, s=s: pose_at(k, lengths, base, float(s)),
                kappas,
            )
            np.testing.assert_allclose(jacobian, numeric, rtol=0.0, atol=1e-9)
    np.testing.assert_array_equal(
        point_jacobian(kappas, lengths, base, lengths.sum()), tip_jacobian(kappas, lengths, base)
    )


@pytest.mark.parametrize("heading", HEADINGS)
def test_jacobian_of_a_straight_arm_is_each_midpoint_lever_along_the_normal(
    heading: float,
) -> None:
    # bending segment i of a straight arm swings the tip sideways by L_i times the distance
    # from the segment's midpoint to the tip; the heading by L_i
    lengths = np.array([0.05, 0.06, 0.07, 0.04])
    jacobian = tip_jacobian(np.zeros(4), lengths, (0.0, 0.0, heading))
    start = np.concatenate(([0.0], np.cumsum(lengths)[:-1]))
    lever = lengths * (lengths.sum() - start - lengths / 2)
    normal = np.array([-math.sin(heading), math.cos(heading)])
    np.testing.assert_allclose(jacobian[:2], np.outer(normal, lever), rtol=1e-14, atol=1e-18)
    np.testing.assert_array_equal(jacobian[2], lengths)


def test_jacobian_of_a_quarter_and_a_full_circle() -> None:
    # one segment from heading 0: x = sin(k L) / k, y = (1 - cos(k L)) / k, so
    # dx/dk = L cos(k L) / k - sin(k L) / k^2 and dy/dk = L sin(k L) / k - (1 - cos(k L)) / k^2
    quarter = math.pi / (2 * LENGTH)
    jacobian = tip_jacobian([quarter], [LENGTH], (0.0, 0.0, 0.0))
    expected = (-1 / quarter**2, LENGTH / quarter - 1 / quarter**2, LENGTH)
    np.testing.assert_allclose(jacobian[:, 0], expected, rtol=1e-13)
    full = 2 * math.pi / LENGTH
    jacobian = tip_jacobian([full], [LENGTH], (0.0, 0.0, 0.0))
    np.testing.assert_allclose(jacobian[:, 0], (LENGTH / full, 0.0, LENGTH), rtol=1e-13, atol=1e-17)


def test_jacobian_is_continuous_across_its_series_branch() -> None:
    # SMALL_HALF_ANGLE switches d sinc / dh to its series: both sides agree to rounding
    threshold = 2 * SMALL_HALF_ANGLE / LENGTH
    for heading in HEADINGS:
        below = tip_jacobian([math.nextafter(threshold, 0.0)], [LENGTH], (0.0, 0.0, heading))
        above = tip_jacobian([threshold], [LENGTH], (0.0, 0.0, heading))
        np.testing.assert_allclose(below, above, rtol=0.0, atol=1e-15)


@pytest.mark.parametrize("near_zero", [False, True])
def test_tip_hessian_matches_differences_of_the_jacobian(near_zero: bool) -> None:
    rng = np.random.default_rng(99 + near_zero)
    for n in (1, 2, 5):
        kappas, lengths, base = random_arm(rng, n, near_zero)
        hessian = tip_hessian(kappas, lengths, base)
        numeric = central_difference(
            lambda k, lengths=lengths, base=base: tip_jacobian(k, lengths, base)[:2], kappas
        )
        np.testing.assert_allclose(hessian, numeric, rtol=0.0, atol=1e-9)
        np.testing.assert_array_equal(hessian, hessian.transpose(0, 2, 1))
