"""The camera's imperfections: noise, dropouts, occlusion bursts, outliers
and exposure-time jitter, applied to the true marker positions.

Invariant: a `Camera` is deterministic from the numpy Generator it is given, and its random
stream is stable. Each effect draws from its own child generator (spawned from the given one in
a fixed order) and draws the same number of numbers per picture (per burst, for occlusions)
whatever the outcomes, so switching one effect on or off, or changing its size, never reshuffles
the draws of the others.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

SCOPES = ("frame", "marker")


@dataclass(frozen=True)
class CameraEffects:
    """Camera imperfections in SI units; 0 switches an effect off.

    Attributes
    ----------
    noise
        Isotropic Gaussian marker position standard deviation [m].
    dropout
        Independent per-marker probability that a marker is missing from a picture.
    occlusion_interval
        Mean time between the starts of occlusion bursts [s] (exponential inter-arrival,
        a Poisson process); 0 = no occlusions.
    occlusion_duration
        Length of one occlusion burst [s].
    occlusion_scope
        "frame": a burst hides every marker; "marker": a burst hides one marker chosen uniformly
        at random per burst.
    outlier_rate
        Independent per-marker probability that a marker is displaced.
    outlier_distance
        Displacement of an outlier [m], in a uniformly random direction.
    jitter
        Standard deviation of the exposure-time jitter [s].
    """

    noise: float = 0.0
    dropout: float = 0.0
    occlusion_interval: float = 0.0
    occlusion_duration: float = 0.0
    occlusion_scope: str = "frame"
    outlier_rate: float = 0.0
    outlier_distance: float = 0.0
    jitter: float = 0.0


def check_effects(
    effects: CameraEffects, period: float, macro_step: float, key: str = "camera"
) -> None:
    """Raise ValueError with a one-line message naming the key of the first bad value.

    Parameters
    ----------
    effects
        The configuration to check.
    period
        Camera frame period [s].
    macro_step
        Plant macro step [s].
    key
        Prefix of the key names in messages (the scenario section).
    """

    def fail(name: str, reason: str) -> ValueError:
        return ValueError(f"{key}.{name}: {reason}")

    for name in ("noise", "occlusion_interval", "occlusion_duration", "outlier_distance", "jitter"):
        value = getattr(effects, name)
        if not math.isfinite(value) or value < 0.0:
            raise fail(name, f"must be finite and not negative, got {value}")
    for name in ("dropout", "outlier_rate"):
        value = getattr(effects, name)
        if not 0.0 <= value <= 1.0:
            raise fail(name, f"must be within [0, 1], got {value}")
    if effects.occlusion_scope not in SCOPES:
        scope = effects.occlusion_scope
        raise fail("occlusion_scope", f"must be one of {', '.join(SCOPES)}, got {scope!r}")
    if effects.occlusion_interval > 0.0 and effects.occlusion_duration <= 0.0:
        raise fail("occlusion_duration", "must be positive when occlusion_interval is set")
    if effects.outlier_rate > 0.0 and effects.outlier_distance <= 0.0:
        raise fail("outlier_distance", "must be positive when outlier_rate is set")
    if not (period > 0.0 and macro_step > 0.0):
        raise fail("rate", f"period {period} s and macro step {macro_step} s must be positive")
    if effects.jitter >= period:
        raise fail("jitter", f"must be below the frame period {period} s, got {effects.jitter}")


@dataclass(frozen=True, slots=True)
class Picture:
    """One picture: measured points (NaN rows for missing markers), shape (M, dims) [m], the
    per-marker flags, shape (M,), and when it was taken.

    `outlier` flags only markers that are present (a missing marker displaces nothing)."""

    frame_index: int
    exposure_tick: int
    exposure_time: float  # [s]
    points: np.ndarray
    dropped: np.ndarray
    occluded: np.ndarray
    outlier: np.ndarray

    @property
    def seen(self) -> np.ndarray:
        """Markers present in the picture, shape (M,)."""
        return ~(self.dropped | self.occluded)


DRAW_BLOCK = 256  # pictures' worth of the noise and dropout streams drawn at a time
JITTER_SIGMAS = 6.0  # a real camera's exposure jitter is bounded: a draw beyond 6 sigma (2e-9)


def exposure_delay_bound(jitter: float, period_ticks: int, macro_step: float) -> int:
    """The latest a camera's exposure falls after its nominal tick [ticks]: the jitter [s]
    (standard deviation) is clamped at JITTER_SIGMAS of it, and below the frame period so that
    pictures stay in order; 0 without jitter. The controller waits for each frame as if it were
    that late (CameraTiming.delay_ticks): a small jitter costs it a few ticks, not a period."""
    if jitter <= 0.0:
        return 0
    return min(period_ticks - 1, math.ceil(JITTER_SIGMAS * jitter / macro_step))


class _Drawn:
    """A random stream's values (as `draw(n)` gives n of them), drawn DRAW_BLOCK pictures at a
    time and taken in order. A stream's values do not depend on how many are drawn at once
    (numpy's Generator keeps nothing between calls), so what `take` gives is, bit for bit, what
    a draw each time would give, in a fraction of the calls."""

    def __init__(self, draw: Callable[[int], np.ndarray]) -> None:
        self._draw = draw
        self._values = draw(0)  # none yet, of the draw's dtype
        self._at = 0

    def take(self, count: int) -> np.ndarray:
        """The next `count` values (a view: read, never written)."""
        at = self._at
        if at + count > len(self._values):
            self._values = np.concatenate((self._values[at:], self._draw(count * DRAW_BLOCK)))
            at = 0
        self._at = at + count
        return self._values[at : at + count]


class Camera:
    """The camera's imperfection model: takes pictures of true marker positions.

    Parameters
    ----------
    effects
        What goes wrong (checked with `check_effects`).
    rng
        Source of every random draw; five child generators are spawned from it in a fixed order
        (jitter, noise, dropout, outlier, occlusion).
    period
        Frame period [s]; the nominal exposure of frame j is at a multiple of it.
    macro_step
        Plant macro step h [s]; exposure times are whole ticks.
    """

    def __init__(
        self, effects: CameraEffects, rng: np.random.Generator, period: float, macro_step: float
    ) -> None:
        check_effects(effects, period, macro_step)
        self.effects = effects
        self.period = period
        self.macro_step = macro_step
        self.period_ticks = round(period / macro_step)
        (
            self._rng_jitter,
            self._rng_noise,
            self._rng_dropout,
            self._rng_outlier,
            self._rng_occlusion,
        ) = rng.spawn(5)
        self._jitter_ticks: dict[int, int] = {}
        self._next_frame = 0
        # the noise stream's draws (scaled by the noise) and the dropout stream's verdicts
        noise, dropout = self._rng_noise, self._rng_dropout
        self._noise = _Drawn(lambda n: noise.standard_normal(n) * effects.noise)
        self._dropped = _Drawn(lambda n: dropout.random(n) < effects.dropout)
        # occlusion bursts: (start, end, marker draw in [0, 1)) in time order
        self._bursts: list[tuple[float, float, float]] = []
        self._next_burst = self._draw_gap(0.0)

    def _draw_gap(self, start: float) -> float:
        """Start time of the burst after one starting at `start` (exponential inter-arrival)."""
        if self.effects.occlusion_interval <= 0.0:
            return math.inf
        return start + float(self._rng_occlusion.exponential(self.effects.occlusion_interval))

    def _jitter_of(self, frame_index: int) -> int:
        """Exposure delay of a frame after its nominal time, in ticks, within [0, period)."""
        if frame_index in self._jitter_ticks:
            return self._jitter_ticks[frame_index]
        if frame_index != self._next_frame:
            raise ValueError(
                f"camera frame {frame_index} out of order: the next frame is {self._next_frame}"
            )
        if self.effects.jitter > 0.0:
            draw = float(self._rng_jitter.normal(0.0, 1.0)) * self.effects.jitter
            ticks = min(max(round(draw / self.macro_step), 0), self.max_delay_ticks)
        else:  # no jitter: no delay (the stream serves jitter alone, so nothing else moves)
            ticks = 0
        self._jitter_ticks[frame_index] = ticks
        self._next_frame += 1
        return ticks

    @property
    def max_delay_ticks(self) -> int:
        """The latest an exposure falls after its nominal tick [ticks] (`exposure_delay_bound`)."""
        return exposure_delay_bound(self.effects.jitter, self.period_ticks, self.macro_step)

    def exposure_tick(self, frame_index: int, nominal_tick: int) -> int:
        """The tick at which frame `frame_index`, nominally exposed at `nominal_tick`, is taken:
        the plant samples the true shape at that tick. Frames must be asked for in order."""
        return nominal_tick + self._jitter_of(frame_index)

    def _occluded(self, time: float, markers: int) -> np.ndarray:
        """Markers hidden by occlusion bursts at `time` (times must not decrease)."""
        if not self._bursts and self._next_burst > time:  # none under way, none due
            return np.zeros(markers, dtype=bool)
        while self._next_burst <= time:
            start = self._next_burst
            choice = float(self._rng_occlusion.random())
            self._bursts.append((start, start + self.effects.occlusion_duration, choice))
            self._next_burst = self._draw_gap(start)
        self._bursts = [b for b in self._bursts if b[1] > time]
        hidden = np.zeros(markers, dtype=bool)
        for start, _, choice in self._bursts:
            if start <= time:
                if self.effects.occlusion_scope == "frame":
                    hidden[:] = True
                else:
                    hidden[min(int(choice * markers), markers - 1)] = True
        return hidden

    def picture(self, frame_index: int, nominal_time: float, true_points: np.ndarray) -> Picture:
        """Take frame `frame_index`, nominally exposed at `nominal_time` [s], of the true marker
        positions `true_points`, shape (M, 2) or (M, 3) [m], sampled at `exposure_tick`."""
        true_points = np.asarray(true_points, dtype=float)
        markers: int
        dims: int
        markers, dims = true_points.shape
        nominal_tick = round(nominal_time / self.macro_step)
        tick = self.exposure_tick(frame_index, nominal_tick)
        self._jitter_ticks.pop(frame_index)
        time = tick * self.macro_step
        e = self.effects
        # fixed draw counts per picture: M x dims normals, M uniforms, M uniforms + M x dims normals
        points = true_points + self._noise.take(markers * dims).reshape(markers, dims)
        dropped = self._dropped.take(markers)
        outlier_draws = self._rng_outlier.random(markers)
        direction = self._rng_outlier.standard_normal((markers, dims))
        outlier = outlier_draws < e.outlier_rate
        occluded = self._occluded(time, markers)
        # most pictures have neither outliers nor missing markers: skip the masked updates (row
        # by row, so the rows that are updated get the same values either way); whether any
        # draw falls below its rate is asked of a handful of Python values (quicker than .any)
        if min(outlier_draws.tolist(), default=1.0) < e.outlier_rate:
            direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-300)
            points[outlier] += e.outlier_distance * direction[outlier]
        if True in dropped.tolist() or self._bursts:
            missing = dropped | occluded
            points[missing] = np.nan
            outlier &= ~missing
        return Picture(frame_index, tick, time, points, dropped.copy(), occluded, outlier)
