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
    curvatures_from_markers,
    forward,
    markers,
    segment_end,
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
