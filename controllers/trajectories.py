"""Curvature reference profiles: step sequences and sines, a pure function of time.

Both programs evaluate the same profile: the controller to track it, the plant to score the run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Sine:
    start: float  # [s]
    amplitude: float  # [1/m]
    frequency: float  # [Hz]
    offset: float = 0.0  # [1/m]


@dataclass(frozen=True)
class CurvatureProfile:
    """Piecewise-constant steps (time [s], curvature [1/m]) followed by an optional sine.

    `steps` must be sorted by time; before the first step the reference is 0. From `sine.start`
    on, the sine replaces the steps.
    """

    steps: tuple[tuple[float, float], ...] = ()
    sine: Sine | None = None
    scale: tuple[float, ...] = field(default=(1.0,))  # per segment

    def value(self, t: float) -> float:
        if self.sine is not None and t >= self.sine.start:
            phase = 2.0 * math.pi * self.sine.frequency * (t - self.sine.start)
            return self.sine.offset + self.sine.amplitude * math.sin(phase)
        kappa = 0.0
        for time, level in self.steps:
            if t >= time:
                kappa = level
        return kappa

    def for_segment(self, segment: int, t: float) -> float:
        """Reference of segment index `segment` (0-based)."""
        return self.scale[segment % len(self.scale)] * self.value(t)

    def step_times(self, duration: float) -> list[tuple[float, float, float]]:
        """(start, end, level) of every step hold that ends before the sine or the run's end."""
        end_of_steps = self.sine.start if self.sine is not None else duration
        holds = []
        for i, (time, level) in enumerate(self.steps):
            end = self.steps[i + 1][0] if i + 1 < len(self.steps) else end_of_steps
            end = min(end, end_of_steps, duration)
            if end > time:
                holds.append((time, end, level))
        return holds
