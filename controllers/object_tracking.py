"""The objects on the table, tracked by their camera markers beside the arm's estimator
(the planar arm's grasp-and-place: robots.planar_arm.controller.grasp_control).

Invariant: an estimate depends only on the sequence of `update` calls (bit-identical reruns).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np

from controllers.bend_filter import REACQUIRE, marker_std
from controllers.estimation import (
    CameraNoise,
    DriveReading,
    Estimate,
    Estimator,
    MarkerFrame,
)


class ObjectTracker:
    """Kalman filters of the objects' centres from their camera markers: per object a
    random-walk position (process noise `drift` [m/sqrt(s)]: an object stays put unless the arm
    moves it) measured with the camera's marker noise, started at its first sighting; a marker
    further than GATE standard deviations from the prediction is an outlier and is dropped,
    unless REACQUIRE pictures in a row say so: then the object has moved (the arm carries it)
    and the filter restarts at the marker."""

    GATE = 5.0  # Mahalanobis distance beyond which a marker is an outlier

    def __init__(self, objects: int, camera: CameraNoise, drift: float = 2e-3) -> None:
        self.x = np.full((objects, 2), np.nan)
        self.P = np.full(objects, np.inf)  # isotropic variance [m^2]
        self.R = marker_std(camera) ** 2
        self.q = drift**2
        self.time = np.full(objects, np.nan)
        self.rejected = np.zeros(objects, int)  # consecutive gated markers

    def update(self, points: np.ndarray, exposure: float) -> int:
        """Fuse one picture's object markers (shape (objects, 2), NaN where unseen); returns the
        number of outliers rejected."""
        gated = 0
        for o, z in enumerate(points):
            if np.isnan(z).any():
                continue
            if np.isnan(self.time[o]) or self.rejected[o] + 1 >= REACQUIRE:
                self.x[o], self.P[o], self.time[o] = z, self.R, exposure
                self.rejected[o] = 0
                continue
            P = self.P[o] + self.q * max(exposure - self.time[o], 0.0)
            S = P + self.R
            innovation = z - self.x[o]
            if float(innovation @ innovation) / S > self.GATE**2:
                gated += 1
                self.rejected[o] += 1
                continue
            self.rejected[o] = 0
            gain = P / S
            self.x[o] = self.x[o] + gain * innovation
            self.P[o], self.time[o] = (1.0 - gain) * P, exposure
        return gated


class WithObjects:
    """An arm estimator plus an ObjectTracker: the arm's markers (the first `markers` of each
    picture) go to the arm's estimator, the rest to the tracker; the estimate carries both."""

    def __init__(self, arm: Estimator, markers: int, tracker: ObjectTracker) -> None:
        self.arm, self.markers, self.tracker = arm, markers, tracker
        self.name = arm.name

    def update(
        self, t: float, drives: Mapping[int, DriveReading], frames: Sequence[MarkerFrame]
    ) -> Estimate:
        gated = 0
        for frame in frames:
            gated += self.tracker.update(frame.points[self.markers :], frame.exposure_time)
        arm_frames = [
            MarkerFrame(exposure_time=f.exposure_time, points=f.points[: self.markers])
            for f in frames
        ]
        estimate = self.arm.update(t, drives, arm_frames)
        return dataclasses.replace(
            estimate, objects=self.tracker.x.copy(), gated=estimate.gated + gated
        )
