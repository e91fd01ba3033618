"""Tests for hil.vision: determinism, a stable random stream, rates within binomial bounds,
occlusion coverage of a Poisson burst process, jitter quantisation, and one-line config errors."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hil.vision import Camera, CameraEffects, Picture, check_effects, exposure_delay_bound

H = 1e-3  # [s]
PERIOD = 0.01  # [s]
TRUE = np.array([[0.0, 0.0], [0.0, 0.06], [0.01, 0.12], [0.03, 0.17]])  # [m]
DEFAULT = CameraEffects(noise=5e-4, dropout=0.01, outlier_rate=0.001, outlier_distance=0.02)


def shoot(effects: CameraEffects, frames: int, seed: int = 7, true=TRUE) -> list[Picture]:
    camera = Camera(effects, np.random.default_rng(seed), PERIOD, H)
    return [camera.picture(j, j * PERIOD, true) for j in range(frames)]


def test_pictures_drawn_in_blocks_are_the_pictures_drawn_one_by_one() -> None:
    """The noise and dropout streams are drawn DRAW_BLOCK pictures at a time: every picture,
    across block boundaries and as the marker count changes, is bit for bit the picture of one
    draw per stream per picture (M x dims normals, M uniforms, M uniforms + M x dims normals)."""
    from hil.vision import DRAW_BLOCK

    effects = CameraEffects(noise=5e-4, dropout=0.2, outlier_rate=0.1, outlier_distance=0.02)
    camera = Camera(effects, np.random.default_rng(11), PERIOD, H)
    _, noise, dropout, outlier, _ = np.random.default_rng(11).spawn(5)
    frames = 2 * DRAW_BLOCK + 37
    for j in range(frames):
        true = TRUE if j % 97 < 60 else TRUE[:3]  # a marker fewer now and then
        markers = len(true)
        picture = camera.picture(j, j * PERIOD, true)
        expected = true + noise.normal(0.0, 1.0, (markers, 2)) * effects.noise
        dropped = dropout.random(markers) < effects.dropout
        hit = outlier.random(markers) < effects.outlier_rate
        direction = outlier.normal(0.0, 1.0, (markers, 2))
        direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-300)
        expected[hit] += effects.outlier_distance * direction[hit]
        expected[dropped] = np.nan
        assert picture.points.view(np.int64).tolist() == expected.view(np.int64).tolist(), j
        assert picture.dropped.tolist() == dropped.tolist()
        assert picture.outlier.tolist() == (hit & ~dropped).tolist()


def binomial_ok(count: int, trials: int, p: float, z: float = 4.5) -> bool:
    """count within z standard deviations of trials p (a 4.5 sigma band: ~1e-5 false failures)."""
    return abs(count - trials * p) <= z * math.sqrt(trials * p * (1.0 - p)) + 1.0


def test_same_seed_same_pictures_other_seed_other_pictures() -> None:
    effects = dataclasses.replace(DEFAULT, jitter=2e-3, occlusion_interval=0.2)
    effects = dataclasses.replace(effects, occlusion_duration=0.05)
    a, b, c = shoot(effects, 300), shoot(effects, 300), shoot(effects, 300, seed=8)
    for p, q in zip(a, b, strict=True):
        np.testing.assert_array_equal(p.points, q.points)
        assert p.exposure_tick == q.exposure_tick
    assert any(
        not np.array_equal(p.points, q.points, equal_nan=True) for p, q in zip(a, c, strict=True)
    )


@pytest.mark.parametrize(
    "switch",
    [
        {"dropout": 0.3},
        {"outlier_rate": 0.2, "outlier_distance": 0.02},
        {"occlusion_interval": 0.1, "occlusion_duration": 0.03, "occlusion_scope": "marker"},
        {"jitter": 3e-3},
    ],
)
def test_switching_an_effect_on_does_not_reshuffle_the_noise_or_dropouts(switch: dict) -> None:
    base = CameraEffects(noise=5e-4, dropout=0.05)
    plain = shoot(base, 400)
    changed = shoot(dataclasses.replace(base, **switch), 400)
    for p, q in zip(plain, changed, strict=True):
        both = p.seen & q.seen & ~q.outlier
        if switch.get("jitter", 0.0) == 0.0:
            # the same true points: the noise of every marker seen in both pictures is unchanged
            np.testing.assert_array_equal(p.points[both], q.points[both])
        if "dropout" not in switch:
            np.testing.assert_array_equal(p.dropped, q.dropped)


def test_dropout_and_outlier_rates_within_binomial_bounds() -> None:
    effects = CameraEffects(dropout=0.1, outlier_rate=0.05, outlier_distance=0.02)
    pictures = shoot(effects, 2500)
    trials = 2500 * len(TRUE)
    dropped = sum(int(p.dropped.sum()) for p in pictures)
    outliers = sum(int(p.outlier.sum()) for p in pictures)
    assert binomial_ok(dropped, trials, 0.1)
    # an outlier is flagged only on a marker that is present
    assert binomial_ok(outliers, trials, 0.05 * 0.9)
    for p in pictures:
        assert np.isnan(p.points[p.dropped]).all()
        assert not np.isnan(p.points[~p.dropped]).any()
        # noise off: an outlier sits exactly outlier_distance away, everything else is exact
        moved = np.linalg.norm(p.points[p.seen] - TRUE[p.seen], axis=1)
        np.testing.assert_allclose(moved, np.where(p.outlier[p.seen], 0.02, 0.0), atol=1e-15)


def test_noise_has_the_configured_standard_deviation() -> None:
    pictures = shoot(CameraEffects(noise=5e-4), 2000)
    errors = np.concatenate([p.points - TRUE for p in pictures]).ravel()
    n = errors.size
    # the sample variance of n normals: relative std sqrt(2 / n)
    assert abs(errors.var() / 5e-4**2 - 1.0) < 4.5 * math.sqrt(2.0 / n)


@pytest.mark.parametrize("scope", ["frame", "marker"])
def test_occlusion_covers_the_poisson_fraction_of_time(scope: str) -> None:
    interval, duration, frames = 0.2, 0.05, 10000
    effects = CameraEffects(
        occlusion_interval=interval, occlusion_duration=duration, occlusion_scope=scope
    )
    pictures = shoot(effects, frames)
    hidden = np.array([p.occluded for p in pictures])
    # a time is covered when a burst started within the last `duration`: 1 - exp(-D / I)
    covered = 1.0 - math.exp(-duration / interval)
    bursts = frames * PERIOD / interval
    tolerance = 4.5 * math.sqrt(bursts) * duration / (frames * PERIOD) + 0.01
    if scope == "frame":
        assert (hidden.all(axis=1) | ~hidden.any(axis=1)).all()
        assert abs(hidden.any(axis=1).mean() - covered) < tolerance
    else:
        per_marker = 1.0 - math.exp(-duration / (interval * len(TRUE)))
        assert abs(hidden.mean() - per_marker) < tolerance
        assert hidden.sum(axis=1).max() <= len(TRUE)
    for p in pictures:
        assert np.isnan(p.points[p.occluded]).all()


def test_jitter_is_quantised_clamped_and_announced_before_the_picture() -> None:
    jitter = 2e-3
    camera = Camera(CameraEffects(jitter=jitter), np.random.default_rng(3), PERIOD, H)
    offsets = []
    for j in range(3000):
        nominal = j * 10
        announced = camera.exposure_tick(j, nominal)
        assert camera.exposure_tick(j, nominal) == announced  # asking twice draws nothing
        picture = camera.picture(j, j * PERIOD, TRUE)
        assert picture.exposure_tick == announced
        assert picture.exposure_time == announced * H
        offsets.append(announced - nominal)
    offsets = np.array(offsets)
    assert offsets.min() == 0 and offsets.max() <= 9
    # the offset is round(N(0, jitter) / h) clamped at 0: positive when the draw exceeds h / 2
    positive = 0.5 * math.erfc(0.5 * H / jitter / math.sqrt(2.0))
    assert binomial_ok(int((offsets > 0).sum()), len(offsets), positive)
    # a jitter near the period reaches the clamp, one tick before the next nominal exposure
    wide = Camera(CameraEffects(jitter=0.009), np.random.default_rng(4), PERIOD, H)
    wide_offsets = [wide.exposure_tick(j, 10 * j) - 10 * j for j in range(200)]
    assert min(wide_offsets) == 0 and max(wide_offsets) == 9
    no_jitter = shoot(CameraEffects(), 50)
    assert [p.exposure_tick for p in no_jitter] == [10 * j for j in range(50)]


def test_the_jitter_bound_is_six_sigma_below_the_period() -> None:
    """What the controller waits for (CameraTiming.delay_ticks): the latest exposure delay the
    camera can draw, 6 sigma rounded up to a tick, below the period; 0 without jitter."""
    assert exposure_delay_bound(0.0, 10, H) == 0
    assert exposure_delay_bound(1e-4, 10, H) == 1
    assert exposure_delay_bound(0.5e-3, 10, H) == 3
    assert exposure_delay_bound(1.5e-3, 10, H) == 9
    assert exposure_delay_bound(2e-3, 10, H) == 9  # 12 ticks: below the period
    assert exposure_delay_bound(2e-3, 40, H) == 12
    small = Camera(CameraEffects(jitter=0.5e-3), np.random.default_rng(5), PERIOD, H)
    assert small.max_delay_ticks == 3
    offsets = [small.exposure_tick(j, 10 * j) - 10 * j for j in range(3000)]
    assert max(offsets) <= 3 and max(offsets) >= 1


def test_three_dimensional_markers() -> None:
    true = np.column_stack([TRUE, np.linspace(0.0, 0.03, len(TRUE))])
    pictures = shoot(dataclasses.replace(DEFAULT, outlier_rate=0.3), 200, true=true)
    for p in pictures:
        assert p.points.shape == (len(TRUE), 3)
        moved = np.linalg.norm(p.points[p.outlier] - true[p.outlier], axis=1)
        assert (moved > 0.015).all()


def test_frames_must_be_taken_in_order() -> None:
    camera = Camera(CameraEffects(jitter=1e-3), np.random.default_rng(0), PERIOD, H)
    with pytest.raises(ValueError, match="out of order"):
        camera.exposure_tick(3, 30)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"noise": -1e-3}, "camera.noise: must be finite and not negative, got -0.001"),
        ({"dropout": 1.5}, "camera.dropout: must be within [0, 1], got 1.5"),
        ({"outlier_rate": -0.1}, "camera.outlier_rate: must be within [0, 1], got -0.1"),
        ({"occlusion_scope": "pixel"}, "camera.occlusion_scope: must be one of frame, marker"),
        ({"occlusion_interval": 1.0}, "camera.occlusion_duration: must be positive"),
        ({"outlier_rate": 0.01}, "camera.outlier_distance: must be positive"),
        ({"jitter": 0.01}, "camera.jitter: must be below the frame period 0.01 s, got 0.01"),
        ({"occlusion_duration": math.nan}, "camera.occlusion_duration: must be finite"),
    ],
)
def test_bad_values_raise_one_line_errors_naming_the_key(change: dict, message: str) -> None:
    with pytest.raises(ValueError) as error:
        check_effects(dataclasses.replace(CameraEffects(), **change), PERIOD, H)
    assert str(error.value).startswith(message)
    assert "\n" not in str(error.value)
    with pytest.raises(ValueError):
        Camera(dataclasses.replace(CameraEffects(), **change), np.random.default_rng(0), PERIOD, H)
