"""The speed work of issue 8 changes no maths: each fast path against its reference.

- The UKF's inlined correction equals filterpy's `UnscentedKalmanFilter.update` with the
  per-marker gate solved by `np.linalg.solve` (the code it replaced), to rounding, on seeded
  random states, covariances and marker subsets for 1 and 6 segments.
- FeaSegment's isothermal Newton solve under vacuum (one exp per iteration) keeps the gas law
  (p_atm + g) V = m R T with the collapsed channel volume, on the side that goes under vacuum.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.kalman import UnscentedKalmanFilter
from synthetic_arm import BASE, SEGMENT, camera_noise

from controllers.arm_ukf import ArmUnscentedEstimator
from hil.vision import CameraEffects
from tests.helpers import simulate

P_ATM = 101325.0


def reference_correct(
    est: ArmUnscentedEstimator, x: np.ndarray, P: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The correction as it was before the speed work: filterpy's update, per-marker solve."""
    seen = ~np.isnan(points).any(axis=1)
    visible = np.flatnonzero(seen[1:]) + 1
    if visible.size == 0:
        return x, P, 0, 0
    fn = est.points_fn
    sigmas = fn.sigma_points(x, P)
    predicted = est._segment_ends(sigmas)[:, visible - 1].reshape(len(sigmas), -1)
    zp = fn.Wm @ predicted
    deviation = predicted - zp
    accepted = []
    for k, m in enumerate(visible):
        block = deviation[:, 2 * k : 2 * k + 2]
        S = (block.T * fn.Wc) @ block + est.sigma**2 * np.eye(2)
        y = points[m] - zp[2 * k : 2 * k + 2]
        if float(y @ np.linalg.solve(S, y)) <= est.gate:
            accepted.append(m)
    gated = visible.size - len(accepted)
    if not accepted:
        return x, P, gated, 0
    which = np.array(accepted)
    n = 2 * est.segments
    ukf = UnscentedKalmanFilter(dim_x=n, dim_z=n, dt=0.0, hx=None, fx=None, points=fn)
    ukf.x, ukf.P, ukf.sigmas_f = x.copy(), P.copy(), sigmas
    ukf.update(
        points[which].ravel(),
        R=est.sigma**2 * np.eye(2 * which.size),
        hx=lambda s: est._markers(s, which),
    )
    return ukf.x, 0.5 * (ukf.P + ukf.P.T), gated, which.size


@pytest.mark.parametrize("segments", [1, 6])
def test_ukf_correction_equals_filterpys_update(segments: int) -> None:
    rng = np.random.default_rng(8)
    noise = camera_noise(CameraEffects(noise=5e-4))
    est = ArmUnscentedEstimator([SEGMENT] * segments, BASE, noise, 0.01)
    n = 2 * segments
    checked = gated_seen = 0
    for _ in range(40):
        x = np.concatenate([rng.uniform(-0.6, 0.6, segments), rng.uniform(-3, 3, segments)])
        A = rng.normal(size=(n, n)) * np.concatenate([np.full(segments, 0.02), np.ones(segments)])
        P = A @ A.T + 1e-6 * np.eye(n)
        truth = x[:segments] + rng.normal(0.0, 0.02, segments)
        points = est._segment_ends(np.concatenate([truth, x[segments:]])[np.newaxis])[0]
        points = np.vstack([[BASE[0], BASE[1]], points]) + rng.normal(0.0, 5e-4, (segments + 1, 2))
        points[rng.random(segments + 1) < 0.2] = np.nan  # dropouts
        if rng.random() < 0.3:
            points[1 + rng.integers(segments)] += 0.05  # an outlier the gate should catch
        fast = est._correct(x, P, points)
        slow = reference_correct(est, x, P, points)
        assert fast[2:] == slow[2:]  # the same markers gated and fused
        np.testing.assert_allclose(fast[0], slow[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(fast[1], slow[1], rtol=1e-7, atol=1e-12 * np.abs(P).max())
        checked += fast[3] > 0
        gated_seen += fast[2] > 0
    assert checked > 20 and gated_seen >= 2  # the cases exercised both paths


def test_vacuum_side_keeps_the_isothermal_gas_law_with_the_collapsed_volume(
    fea_segment_fmu,  # noqa: ANN001
) -> None:
    def piston(t: float) -> dict[str, float]:
        return {"x_piston": 0.025 + 0.02 * math.sin(2 * math.pi * 2.0 * t)}

    r = simulate(fea_segment_fmu, 0.5, ["theta", "p_a", "p_b", "v_a", "v_b"], {}, piston)
    assert np.ptp(r["theta"]) > 0.1  # it bends: the channel's bend term is in play
    for side in "ab":
        assert r[f"p_{side}"].min() < -10e3  # this side went well under vacuum
        pv = (r[f"p_{side}"] + P_ATM) * r[f"v_{side}"]
        assert np.max(np.abs(pv / pv[0] - 1.0)) < 1e-9
