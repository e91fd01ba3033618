"""The soft fish's controller side (issue 13): its configuration, the head-pose Kalman filter and
the manoeuvre controller (escape turns, forward swimming, a closed-loop heading).

The fish's on-board controller sees what a real one would: ValveStatus1..2 (valve state, channel
gauge pressure, faults), CanisterStatus (canister and supply pressure, gas left) and the overhead
camera's markers (0 the nose, 1 the head-tail joint, 2 the tail tip). It commands ValveCommand1
(channel a: bends the tail left and turns the head left, yaw up) and ValveCommand2 (channel b,
right) every cycle with the time the supply is still to stay open from the next SYNC, so a pulse
ends on the valve driver's clock and a silent controller leaves the valves vented.

Turn angle to valve time: by a calibration table of the heading the fish keeps after an escape turn
against the valve-open time, measured offline on the three fish FMUs (see `CALIBRATION` and README,
"The soft fish"), not by the controller itself; the controller interpolates it (it is monotonic),
and in the heading task corrects what remains with the swimming strokes. Gas budget: manoeuvres left
= usable gas (gas left minus the mass at which the canister can no longer hold the regulator's set
pressure) over the gas per manoeuvre, measured from CanisterStatus as the fish goes (a model
estimate before the first manoeuvre). Invariant: no pulse starts while a channel is still venting
from the previous manoeuvre (except the alternating strokes of swimming, where the other side vents
as one fills), and none once the supply has fallen below the set pressure.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from filterpy.kalman import KalmanFilter

from controllers.config import CameraTiming, config_from_json
from controllers.estimation import MarkerFrame
from rigbus.protocol import GenericFrame, Protocol

TASKS = ("escape", "swim", "heading")
MODES = ("idle", "escape", "swim", "turn", "hold", "venting", "no gas")  # FishState.mode
IDLE, ESCAPE, SWIM, TURN, HOLD, VENTING, NO_GAS = range(len(MODES))
VALVE_CLOSED = 0  # ValveStatus.state: closed and vented
FAULT_NO_SUPPLY = 1
MARKERS = 3  # nose, joint, tail tip
STALE_AFTER = 0.1  # [s] without a usable picture the estimate is no longer valid
GATE_CHI2 = 16.0  # Mahalanobis gate of a camera measurement (3 dof: p < 0.2 %)

# The fish's kept heading change [rad] after an escape turn against the valve-open time [s]
# (FishBody defaults, 1.8 mm nozzle, 400 kPa supply; the yaw 0.8 s after the pulse, when the
# fish has nearly come to rest in yaw), measured offline with the FMUs coupled at 1 ms as in
# tests/test_fish_fmus.py (its `escape` helper); it does not follow other body or valve values.
CALIBRATION: tuple[tuple[float, float], ...] = tuple(
    (t, math.radians(degrees))
    for t, degrees in (
        (0, 0),
        (0.01, 0.78),
        (0.02, 2.11),
        (0.03, 8.04),
        (0.04, 16.56),
        (0.05, 26.03),
        (0.06, 35.47),
        (0.08, 52.52),
        (0.1, 67.09),
        (0.12, 79.57),
        (0.14, 90.23),
        (0.16, 99.88),
        (0.2, 117.46),
    )
)


@dataclass(frozen=True)
class FishConfig:
    """Everything the fish's controller knows (controller.json). Angles in rad, times in s."""

    robot: str
    control_period: float
    cycles: int
    camera_timing: CameraTiming  # markers: 3 (nose, joint, tail tip)
    task: str = "escape"
    start: float = 0.05  # first manoeuvre [s]
    side: int = 1  # escape: valve 1 (turn left) or 2 (turn right)
    turn_angle: float = math.radians(60.0)  # escape: heading change wanted (open_time 0)
    open_time: float = 0.0  # escape: valve-open time [s]; 0 takes it from the calibration
    calibration: tuple[tuple[float, float], ...] = CALIBRATION
    frequency: float = 2.0  # swim: tail beats per second
    duty: float = 0.1  # swim: share of each half beat a side's valve is open
    heading: float = 0.0  # heading task: commanded heading [rad]
    heading_gain: float = 2.0  # heading task: stroke asymmetry per rad of heading error
    tolerance: float = math.radians(10.0)  # heading task: held within it
    retune_share: float = 3.0  # heading task: another escape turn beyond this many tolerances
    deadband: float = math.radians(3.0)  # heading task: a corrective stroke beyond it
    settle_time: float = 0.05  # heading task: the head at rest this long after a turn [s]
    rest_rate: float = math.radians(60.0)  # heading task: at rest below this yaw rate [rad/s]
    settle_max: float = 0.3  # heading task: swim on at the latest this long after a turn [s]
    p_set: float = 400e3  # the regulator's set pressure [Pa abs]
    gas_reserve: float = 0.0  # canister mass that can no longer hold p_set [kg]
    gas_per_manoeuvre: float = 1e-4  # model estimate before the first is measured [kg]
    camera_noise: float = 5e-4  # [m] per marker coordinate (sigma)
    head_length: float = 0.14  # nose to the head-tail joint [m]
    policy: str = "strict"
    timeout: float = 10.0

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> FishConfig:
        """Read a config; wrong or missing keys raise ValueError naming the key."""
        config: FishConfig = config_from_json(cls, text)
        if config.task not in TASKS:
            raise ValueError(f"task: {config.task!r} is not one of {', '.join(TASKS)}")
        if config.side not in (1, 2):
            raise ValueError(f"side: must be 1 or 2, got {config.side}")
        if config.control_period <= 0 or config.cycles < 0 or config.timeout <= 0:
            raise ValueError("control_period and timeout must be positive, cycles not negative")
        if not 0.0 < config.duty <= 1.0 or config.frequency <= 0.0:
            raise ValueError("duty must be in (0, 1], frequency positive")
        angles = [a for _, a in config.calibration]
        if len(angles) < 2 or any(b <= a for a, b in zip(angles, angles[1:], strict=False)):
            raise ValueError("calibration: needs at least two points, angles increasing")
        return config


def wrap(angle: float) -> float:
    """An angle wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def open_time_for(calibration: Sequence[tuple[float, float]], angle: float) -> float:
    """The valve-open time [s] for a kept heading change `angle` [rad], interpolated in the
    calibration table (clamped at its ends)."""
    times = [t for t, _ in calibration]
    angles = [a for _, a in calibration]
    return float(np.interp(abs(angle), angles, times))


@dataclass(frozen=True)
class FishEstimate:
    """The head's estimated pose at the cycle's time: joint x, y [m], yaw [rad] (unwrapped),
    yaw rate [rad/s]; `valid` once a camera picture has been used."""

    x: float
    y: float
    yaw: float
    yaw_rate: float
    valid: bool


class HeadKalman:
    """A linear Kalman filter (filterpy) of the head pose: state (x, y, yaw, vx, vy, yaw rate),
    constant velocity with white-noise accelerations; measurements of the joint's position and
    the heading from nose to joint, each picture applied at its exposure time (the filter is
    kept at the last exposure and predicted forward to the cycle's time for the estimate), and
    gated so that an outlier marker is dropped rather than believed."""

    def __init__(self, config: FishConfig) -> None:
        self.config = config
        kf = KalmanFilter(dim_x=6, dim_z=3)
        kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
        sigma_yaw = math.sqrt(2.0) * config.camera_noise / config.head_length
        kf.R = np.diag([config.camera_noise**2, config.camera_noise**2, sigma_yaw**2])
        kf.P = np.diag([1.0, 1.0, 10.0, 1.0, 1.0, 100.0])
        self.kf = kf
        self.time: float | None = None  # the filter's time (last exposure)
        self.rejected = 0
        # white-noise accelerations [m/s^2], [rad/s^2]: a fast start reaches ~100 m/s^2 and
        # several hundred rad/s^2
        self.q = np.array([30.0, 30.0, 400.0])

    def _predict(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        F = np.eye(6)
        F[0:3, 3:6] = dt * np.eye(3)
        G = np.vstack([0.5 * dt**2 * np.eye(3), dt * np.eye(3)])
        Q = G @ np.diag(self.q**2) @ G.T
        return F, Q

    def update(self, t: float, readings: Mapping[Any, Any], frames: Sequence[MarkerFrame]) -> Any:
        for frame in frames:
            points = frame.points
            if np.isnan(points[0]).any() or np.isnan(points[1]).any():
                continue
            joint, nose = points[1], points[0]
            yaw = math.atan2(nose[1] - joint[1], nose[0] - joint[0])
            if self.time is None:
                self.kf.x = np.array([joint[0], joint[1], yaw, 0.0, 0.0, 0.0])
                self.time = frame.exposure_time
                continue
            dt = frame.exposure_time - self.time
            if dt > 0.0:
                F, Q = self._predict(dt)
                self.kf.predict(F=F, Q=Q)
                self.time = frame.exposure_time
            z = np.array([joint[0], joint[1], 0.0])
            z[2] = self.kf.x[2] + wrap(yaw - self.kf.x[2])  # unwrapped near the prediction
            y = z - self.kf.H @ self.kf.x
            S = self.kf.H @ self.kf.P @ self.kf.H.T + self.kf.R
            if float(y @ np.linalg.solve(S, y)) > GATE_CHI2:
                self.rejected += 1
                continue
            self.kf.update(z)
        if self.time is None:
            return FishEstimate(0.0, 0.0, 0.0, 0.0, False)
        x = self.kf.x.copy()
        dt = max(0.0, t - self.time)
        # out of the camera's view the estimate is not dead-reckoned beyond STALE_AFTER: a
        # constant-velocity guess of a swimming fish's yaw diverges within a beat
        x[0:3] += min(dt, STALE_AFTER) * x[3:6]
        valid = dt <= STALE_AFTER
        return FishEstimate(float(x[0]), float(x[1]), float(x[2]), float(x[5]), valid)


class FishControl:
    """Escape turns, swimming strokes and the heading loop, with venting and the gas budget."""

    def __init__(self, config: FishConfig, protocol: Protocol) -> None:
        self.config = config
        self.mode = IDLE
        self.pulse_end = [0.0, 0.0]  # when each valve's supply closes [s]
        self.manoeuvres = 0
        self.gas_start: float | None = None  # gas left when the first manoeuvre started
        self.gas_per = config.gas_per_manoeuvre
        self.left = 255
        self.next_stroke = config.start
        self.stroke_side = 0
        self.turned = False  # heading task: the first turn is done
        self.turn_done_at = math.inf
        self.mean_yaw: float | None = None  # heading task: yaw averaged over about a beat
        self.rest_since: float | None = None  # heading task: the head at rest since [s]
        self.corrected_at = -math.inf  # heading task: the last corrective stroke [s]
        self.shown = protocol.signal_range("FishState", "heading_ref")

    # ------------------------------------------------------------------ gas

    def _gas(self, readings: Mapping[Any, Any]) -> bool:
        """Update the gas budget; False once the supply cannot hold its set pressure."""
        canister = readings.get(("CanisterStatus", None))
        if canister is None:
            return True
        gas = float(canister.signals["gas_left"])
        if self.gas_start is not None and self.manoeuvres > 0 and self.gas_start > gas:
            self.gas_per = (self.gas_start - gas) / self.manoeuvres
        usable = gas - self.config.gas_reserve
        self.left = max(0, min(255, math.floor(usable / self.gas_per))) if self.gas_per > 0 else 255
        supplied = float(canister.signals["p_supply"]) >= 0.99 * self.config.p_set
        faults = any(
            int(readings[("ValveStatus", n)].signals["fault"]) & FAULT_NO_SUPPLY
            for n in (1, 2)
            if ("ValveStatus", n) in readings
        )
        if not supplied or faults or self.mode == NO_GAS:
            # latched: a canister does not refill (a channel pushing gas back through an open
            # valve can lift the supply for a moment, not the budget)
            self.left = 0
            return False
        return True

    def _vented(self, readings: Mapping[Any, Any]) -> bool:
        return all(
            int(readings[("ValveStatus", n)].signals["state"]) == VALVE_CLOSED
            for n in (1, 2)
            if ("ValveStatus", n) in readings
        )

    def _pulse(self, side: int, t_open: float, at: float, readings: Mapping[Any, Any]) -> None:
        """Open valve `side` (0: a, 1: b) for `t_open` from the next SYNC at `at`."""
        if t_open <= 0.0:
            return
        if self.gas_start is None:
            canister = readings.get(("CanisterStatus", None))
            self.gas_start = float(canister.signals["gas_left"]) if canister else None
        self.pulse_end[side] = at + t_open
        self.manoeuvres += 1

    # ------------------------------------------------------------------ the cycle

    def compute(
        self, cycle: int, t: float, estimate: FishEstimate, readings: Mapping[Any, Any]
    ) -> list[Any]:
        c = self.config
        T = c.control_period
        at = t + T  # commands act from the next SYNC
        has_gas = self._gas(readings)
        busy = any(end > at for end in self.pulse_end)
        if not has_gas:
            self.mode = NO_GAS
            self.pulse_end = [min(end, at) for end in self.pulse_end]
        elif c.task == "escape":
            self._escape(at, busy, readings)
        elif c.task == "swim":
            self._swim(at, readings)
        else:
            self._heading(at, busy, estimate, readings)
        frames: list[Any] = []
        for n in (1, 2):
            remaining = max(0.0, self.pulse_end[n - 1] - at)
            vent = self.mode in (NO_GAS, VENTING) and remaining == 0.0
            frames.append(
                GenericFrame(
                    "ValveCommand",
                    n,
                    {"open_time": round(remaining, 4), "vent": int(vent), "counter": cycle % 256},
                )
            )
        lo, hi = self.shown
        heading_ref = c.heading if c.task == "heading" else 0.0
        frames.append(
            GenericFrame(
                "FishState",
                None,
                {
                    "mode": self.mode,
                    "manoeuvre": self.manoeuvres % 256,
                    "heading_ref": min(max(wrap(heading_ref), lo), hi),
                    "heading_est": min(max(wrap(estimate.yaw), lo), hi),
                    "manoeuvres_left": self.left,
                    "counter": cycle % 256,
                },
            )
        )
        return frames

    def _escape(self, at: float, busy: bool, readings: Mapping[Any, Any]) -> None:
        c = self.config
        if self.manoeuvres == 0:
            if at >= c.start and self._vented(readings):
                t_open = c.open_time or open_time_for(c.calibration, c.turn_angle)
                self._pulse(c.side - 1, t_open, at, readings)
                self.mode = ESCAPE
            return
        self.mode = ESCAPE if busy else VENTING if not self._vented(readings) else IDLE

    def _swim(
        self, at: float, readings: Mapping[Any, Any], bias: float = 0.0, correction: float = 0.0
    ) -> None:
        """Alternate the sides: a stroke every half beat, open `duty` of it; `bias` (-1..1)
        lengthens side a's strokes and shortens side b's (turning left), or the reverse;
        `correction` [rad] (heading task: the beat-averaged heading error beyond the deadband)
        makes the next stroke on the side that turns towards the reference at least as long
        as the calibration's open time for that turn."""
        c = self.config
        if at < c.start:
            return
        self.mode = SWIM
        half = 0.5 / c.frequency
        if at + 1e-9 >= self.next_stroke:
            side = self.stroke_side
            share = 1.0 + (bias if side == 0 else -bias)
            t_open = min(c.duty * half * share, 0.95 * half)
            if correction != 0.0 and side == (0 if correction > 0.0 else 1):
                # sized by the inverse of the calibration; at most once a beat, so that the
                # beat-averaged heading has seen the last one before the next is sized
                t_open = max(t_open, min(open_time_for(c.calibration, correction), 0.95 * half))
                self.corrected_at = at
            self._pulse(side, t_open, at, readings)
            self.stroke_side = 1 - side
            self.next_stroke += half

    def _heading(
        self, at: float, busy: bool, estimate: FishEstimate, readings: Mapping[Any, Any]
    ) -> None:
        """The heading task: an escape turn towards the commanded heading, then swimming
        strokes whose asymmetry holds it (another turn if the heading drifts beyond
        `retune_share` tolerances)."""
        c = self.config
        if not estimate.valid or at < c.start:
            if self.turned and not busy:
                self.mode = HOLD  # out of view: no strokes, the fish glides on its heading
            return
        half = 0.5 / c.frequency
        # the yaw averaged over about one beat: the strokes rock the head about its mean
        alpha = min(1.0, c.control_period / (2.0 * half))
        self.mean_yaw = (
            estimate.yaw
            if self.mean_yaw is None
            else self.mean_yaw + alpha * (estimate.yaw - self.mean_yaw)
        )
        if busy and self.mode == TURN:
            return
        error = wrap(c.heading - estimate.yaw)
        if (self.mode == TURN or self.mode == VENTING) and not self._come_to_rest(
            at, estimate, readings
        ):
            return
        if not self.turned or (
            abs(wrap(c.heading - self.mean_yaw)) > c.retune_share * c.tolerance
            and self.mode != HOLD
        ):
            self._turn(at, error, readings)
            return
        self._hold_heading(at, half, self.mean_yaw, readings)

    def _come_to_rest(self, at: float, estimate: FishEstimate, readings: Mapping[Any, Any]) -> bool:
        """After a turn: vent and let the head come to rest before swimming on; True once it
        has (the strokes then go on, mode HOLD). At rest for `settle_time`, not for one cycle:
        the yaw rate also passes through zero at the turn's overshoot, tens of degrees beyond
        where the head comes to rest (or at the latest `settle_max` after the pulse: the head's
        yaw mode rings on, and the estimated yaw rate is noisy)."""
        c = self.config
        self.mode = VENTING
        late = at - max(self.pulse_end) >= c.settle_max
        if not self._vented(readings) or abs(estimate.yaw_rate) > c.rest_rate:
            self.rest_since = None
            if not late:
                return False
        if self.rest_since is None:
            self.rest_since = at
        if at - self.rest_since < c.settle_time and not late:
            return False
        self.mean_yaw = estimate.yaw  # the beat average starts again where the head rests
        # the strokes go on alternating from the turn: the first is on the other side
        self.stroke_side = 1 - self.stroke_side
        self.next_stroke = at
        self.corrected_at = at
        self.mode = HOLD
        return True

    def _turn(self, at: float, error: float, readings: Mapping[Any, Any]) -> None:
        """An escape turn by the heading `error` [rad] (valve time from the calibration), once
        both channels are vented."""
        if self._vented(readings):
            side = 0 if error > 0.0 else 1
            self._pulse(side, open_time_for(self.config.calibration, error), at, readings)
            self.stroke_side = side
            self.turned = True
            self.mode = TURN

    def _hold_heading(
        self, at: float, half: float, mean_yaw: float, readings: Mapping[Any, Any]
    ) -> None:
        """Swim with strokes biased by the beat-averaged heading error, a corrective stroke at
        most once a beat beyond the deadband."""
        c = self.config
        error = wrap(c.heading - mean_yaw)
        bias = max(-1.0, min(1.0, c.heading_gain * error))
        correction = 0.0
        if abs(error) > c.deadband and at - self.corrected_at >= 2.0 * half - 1e-9:
            correction = error
        self._swim(at, readings, bias, correction)
        self.mode = HOLD


def make_estimator(config: FishConfig) -> HeadKalman:
    return HeadKalman(config)


def make_controller(config: FishConfig, protocol: Protocol) -> FishControl:
    return FishControl(config, protocol)


def expected(config: FishConfig) -> set[tuple[str, int | None]]:
    """The status frames every cycle must bring: both valves' and the canister's."""
    return {("ValveStatus", 1), ("ValveStatus", 2), ("CanisterStatus", None)}


def readings(status: Mapping[tuple[str, int | None], Any]) -> dict[Any, Any]:
    """What the estimator and controller see of the cycle's status frames: the frames."""
    return dict(status)


config_class = FishConfig
