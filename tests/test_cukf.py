"""The arm UKF's prediction and correction in C (`controllers.cukf`) against the numpy code it
speeds up (the reference, and the fallback): the same markers gated and fused, the same state
and covariance to rounding, the same innovation; what C cannot decide (no Cholesky factor) is
left to numpy; `SOFTHIL_UKF` chooses, and a misspelt value is one line."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from synthetic_arm import BASE, SEGMENT, camera_noise

from controllers import cukf
from controllers.arm_ukf import ArmUnscentedEstimator
from hil.vision import CameraEffects

needs_c = pytest.mark.skipif(cukf.load() is None, reason=f"no C UKF here: {cukf.failure()}")


def test_the_c_ukf_builds_where_gcc_is() -> None:
    """Where the README's install holds (gcc), the C path is the one in use: a broken build
    would otherwise pass every other test here on the numpy path."""
    if shutil.which("gcc") is None or cukf.failure() == f"{cukf.ENV}=python":
        pytest.skip("no gcc, or the numpy path chosen")
    assert cukf.load() is not None, cukf.failure()


def estimator(segments: int, base: tuple[float, float, float] = BASE) -> ArmUnscentedEstimator:
    return ArmUnscentedEstimator(
        [SEGMENT] * segments, base, camera_noise(CameraEffects(noise=5e-4)), 0.01
    )


def cases(est: ArmUnscentedEstimator, count: int, seed: int):  # noqa: ANN201
    """Seeded states, covariances and pictures: dropouts, outliers and, now and then, a picture
    far from the state (every marker gated) or with no marker at all."""
    rng = np.random.default_rng(seed)
    N, n = est.segments, 2 * est.segments
    for k in range(count):
        x = np.concatenate([rng.uniform(-0.6, 0.6, N), rng.uniform(-3, 3, N)])
        A = rng.normal(size=(n, n)) * np.concatenate([np.full(N, 0.02), np.ones(N)])
        P = A @ A.T + 1e-6 * np.eye(n)
        truth = x[:N] + rng.normal(0.0, 0.02, N)
        points = est._segment_ends(np.concatenate([truth, x[N:]])[np.newaxis])[0]
        points = np.vstack([est.base[:2], points]) + rng.normal(0.0, 5e-4, (N + 1, 2))
        points[rng.random(N + 1) < 0.2] = np.nan
        if rng.random() < 0.3:
            points[1 + rng.integers(N)] += 0.05  # an outlier
        if k % 13 == 5:
            points[1:] += 0.5  # far from the state: every marker gated
        if k % 17 == 3:
            points[1:] = np.nan  # nothing seen
        yield x, P, points, rng.normal(0.0, 2e3, N)


@needs_c
@pytest.mark.parametrize("segments", [1, 2, 6])
@pytest.mark.parametrize("base", [BASE, (0.013, -0.021, 1.2)])
def test_the_c_correction_equals_numpys(segments: int, base: tuple[float, float, float]) -> None:
    est = estimator(segments, base)
    assert est._c is not None
    seen = {"fused": 0, "gated": 0, "all gated": 0, "none seen": 0}
    for x, P, points, _ in cases(est, 60, segments):
        est.innovation = est.innovation_covariance = None
        fast = est._correct(x, P, points)
        fast_innovation = (est.innovation, est.innovation_covariance)
        est.innovation = est.innovation_covariance = None
        slow = est._correct_numpy(x, P, points)
        assert fast[2:] == slow[2:]  # the same markers gated and fused
        # to rounding, as the numpy path agrees with filterpy's (test_speed_equivalence): the
        # gain solves a 2m x 2m system, whose conditioning scales the rounding
        np.testing.assert_allclose(fast[0], slow[0], rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(fast[1], slow[1], rtol=1e-7, atol=1e-12 * np.abs(P).max())
        np.testing.assert_array_equal(fast[1], fast[1].T)  # symmetric exactly
        if slow[3]:
            np.testing.assert_allclose(fast_innovation[0], est.innovation, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(
                fast_innovation[1], est.innovation_covariance, rtol=1e-9, atol=1e-16
            )
        else:  # nothing fused: the state is returned as it was, and no innovation
            assert fast[0] is x and fast[1] is P and fast_innovation == (None, None)
        seen["fused"] += fast[3] > 0
        seen["gated"] += fast[2] > 0
        seen["all gated"] += fast[2] > 0 and fast[3] == 0
        seen["none seen"] += fast[2] == fast[3] == 0
    assert seen["fused"] > 30 and min(seen.values()) >= 1, seen


@needs_c
@pytest.mark.parametrize("segments", [1, 6])
def test_the_c_prediction_equals_numpys(segments: int) -> None:
    est = estimator(segments)
    for x, P, _, u in cases(est, 20, 10 + segments):
        for dt in (0.01, 0.0037, 0.0):
            fast, slow = est._predict(x, P, u, dt), est._predict_numpy(x, P, u, dt)
            np.testing.assert_allclose(fast[0], slow[0], rtol=1e-12, atol=1e-14)
            np.testing.assert_allclose(fast[1], slow[1], rtol=1e-10, atol=1e-14 * np.abs(P).max())
            np.testing.assert_array_equal(fast[1], fast[1].T)
            assert fast[0] is not x and fast[1] is not P  # fresh arrays: the history keeps them


@needs_c
@pytest.mark.parametrize("kind", ["indefinite", "singular"])
def test_a_covariance_without_a_cholesky_factor_is_left_to_numpy(kind: str) -> None:
    """Rounding can leave P slightly indefinite, and a state known exactly has a zero variance;
    numpy's path then takes the symmetric square root of the positive part. The C code
    declines (a zero pivot included), and the result is numpy's exactly."""
    est = estimator(2)
    x, P, points, _ = next(cases(est, 1, 3))
    if kind == "indefinite":
        values, vectors = np.linalg.eigh(P)
        values[0] = -1e-9
        P = (vectors * values) @ vectors.T
    else:
        P = P.copy()
        P[1, :] = P[:, 1] = 0.0  # theta_2 known exactly
    assert est._c is not None and est._c.correct(x, P, points) is None
    fast, slow = est._correct(x, P, points), est._correct_numpy(x, P, points)
    assert fast[2:] == slow[2:] and slow[3] > 0
    assert np.isfinite(fast[0]).all()
    np.testing.assert_array_equal(fast[0], slow[0])
    np.testing.assert_array_equal(fast[1], slow[1])


def test_the_numpy_path_alone_when_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    """SOFTHIL_UKF=python: no library is built or loaded; the estimator works in numpy."""
    monkeypatch.setattr(cukf._part, "value", None)
    monkeypatch.setattr(cukf._part, "failure", None)
    monkeypatch.setenv(cukf.ENV, "python")
    assert cukf.load() is None and cukf.failure() == "SOFTHIL_UKF=python"
    est = estimator(2)
    assert est._c is None
    x, P, points, _ = next(cases(est, 1, 4))
    np.testing.assert_array_equal(
        est._correct(x, P, points)[0], est._correct_numpy(x, P, points)[0]
    )


def test_a_misspelt_ukf_setting_is_one_line_in_hil_and_the_controller(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from controllers.__main__ import main as controller_main
    from hil.cli import main as hil_main

    for value, meant in (("", "c"), ("C", "c"), (" Python ", "python")):
        monkeypatch.setenv(cukf.ENV, value)
        assert cukf.setting() == meant
    monkeypatch.setenv(cukf.ENV, "numpy")
    assert hil_main(["scenarios"]) == 1
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("hil: error: SOFTHIL_UKF='numpy': must be c")
    assert err.count("\n") == 1
    (tmp_path / "controller.json").write_text("{}")
    assert controller_main(["--config", str(tmp_path / "controller.json")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("controller: error: SOFTHIL_UKF='numpy'") and err.count("\n") == 1


def test_a_damaged_cache_entry_is_built_again(tmp_path: Path) -> None:
    """A cached library that does not load (cut short, overwritten) is compiled again, not
    silently replaced by the slow path. In fresh processes: this one has the library loaded,
    and the dynamic loader would hand it back by its path without reading the file."""
    if shutil.which("gcc") is None:
        pytest.skip("no gcc")
    env = {**os.environ, "SOFTHIL_CACHE_DIR": str(tmp_path)}
    env.pop(cukf.ENV, None)
    probe = "from controllers import cukf; print(cukf.load() is not None, cukf.failure())"
    run = [sys.executable, "-c", probe]
    assert subprocess.run(run, env=env, capture_output=True, text=True).stdout == "True None\n"
    (built,) = (tmp_path / "ukf").glob("cukf-*.so")
    built.write_bytes(b"not a library")
    assert subprocess.run(run, env=env, capture_output=True, text=True).stdout == "True None\n"
    assert built.read_bytes()[:4] == b"\x7fELF"
