"""A synthetic planar arm and camera for the estimator tests: no FMUs.

Each segment bends as I theta'' + d theta' + k theta = G_a dp(t) + w, integrated exactly per
macro step h (matrix exponential with dp held over the step); w is an unmodelled torque held
over each control period T with a given standard deviation. The camera (hil.vision) exposes frame
j nominally at j T, samples the true shape at its (jittered) exposure tick, and the frame is
delivered at the first SYNC at or after exposure + latency, as the plant does.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from controllers.estimation import BendModel, CameraNoise, DriveReading, MarkerFrame
from controllers.kinematics import markers
from hil.vision import Camera, CameraEffects

H = 1e-3  # [s] macro step
T = 0.01  # [s] control period
LATENCY_TICKS = 6
SEGMENT = BendModel(length=0.06, inertia=0.03 * 0.06**2 / 20, k_bend=0.025, d_bend=6e-3, G_a=7.7e-7)
BASE = (0.0, 0.0, np.pi / 2)


@dataclass
class Run:
    """Cycles for an estimator, and the truth at each SYNC: kappa shape (cycles, N) [1/m]."""

    cycles: list[tuple[float, dict[int, DriveReading], list[MarkerFrame]]]
    kappa: np.ndarray
    outliers: np.ndarray  # outlier markers the camera delivered, per marker, shape (N + 1,)
    delivered: int  # markers the camera delivered


def camera_noise(effects: CameraEffects) -> CameraNoise:
    """What the controller is told of a camera with these effects."""
    return CameraNoise(
        noise=effects.noise,
        dropout=effects.dropout,
        outlier_rate=effects.outlier_rate,
        outlier_distance=effects.outlier_distance,
        rate=1.0 / T,
        latency=LATENCY_TICKS * H,
    )


def simulate(
    pressure: Callable[[float], np.ndarray],
    effects: CameraEffects,
    cycles: int,
    seed: int,
    segments: int = 3,
    torque_std: float = 0.0,
    bend: BendModel = SEGMENT,
) -> Run:
    """Simulate `cycles` control periods with pressure differences `pressure(t)`, shape (N,) [Pa],
    sampled every macro step."""
    rng = np.random.default_rng(seed)
    camera = Camera(effects, rng.spawn(1)[0], T, H)
    torque_rng = rng.spawn(1)[0]
    A = np.array([[0.0, 1.0], [-bend.k_bend / bend.inertia, -bend.d_bend / bend.inertia]])
    augmented = np.zeros((4, 4))
    augmented[:2, :2] = A
    augmented[:2, 2] = [0.0, bend.G_a / bend.inertia]
    augmented[:2, 3] = [0.0, 1.0 / bend.inertia]
    transition = expm(augmented * H)
    F, G, Gw = transition[:2, :2], transition[:2, 2], transition[:2, 3]
    lengths = [bend.length] * segments
    ticks_per_cycle = round(T / H)
    x = np.zeros((segments, 2))
    pending: list[tuple[int, MarkerFrame]] = []
    out, truth = [], []
    outliers, delivered = np.zeros(segments + 1, dtype=int), 0
    torque = np.zeros(segments)
    next_exposure = camera.exposure_tick(0, 0)
    frame = 0
    for c in range(cycles):
        sync_tick = c * ticks_per_cycle
        t = sync_tick * H
        dp = pressure(t)
        drives = {n + 1: DriveReading(0.025, float(dp[n]), 0.0) for n in range(segments)}
        due = [f for tick, f in pending if tick <= sync_tick]
        pending = [(tick, f) for tick, f in pending if tick > sync_tick]
        out.append((t, drives, due))
        truth.append(x[:, 0] / bend.length)
        torque = torque_rng.normal(0.0, 1.0, segments) * torque_std
        for k in range(sync_tick, sync_tick + ticks_per_cycle):
            if k == next_exposure:
                true_points = markers(x[:, 0] / bend.length, lengths, BASE)
                picture = camera.picture(frame, frame * T, true_points)
                outliers += picture.outlier
                delivered += int(picture.seen.sum())
                pending.append(
                    (k + LATENCY_TICKS, MarkerFrame(picture.exposure_time, picture.points))
                )
                frame += 1
                next_exposure = camera.exposure_tick(frame, frame * ticks_per_cycle)
            u = pressure(k * H)
            x = x @ F.T + u[:, np.newaxis] * G + torque[:, np.newaxis] * Gw
    return Run(out, np.array(truth), outliers, delivered)
