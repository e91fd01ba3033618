"""The controller node: a separate program that sees the rig only through the CAN bus.

It is the SYNC producer (as a CANopen master on a rig). Cycle c:
  1. wait for the period (real-time clock) or not at all (lockstep), send SYNC(c);
  2. collect the camera marker frames and every drive's status frame echoing c (the plant sends
     camera frames first, so the last status frame closes the cycle on an ordered bus);
  3. estimate each segment's curvature from the newest complete camera frame (chord-angle PCC
     inverse), run the curvature PI, send the drive commands and the controller-state frames;
then SYNC(c+1). Commands computed from the status of c act from SYNC(c+1): one control period
of computation delay, as on a rig. Missing or stale frames follow the policy: `strict` stops with
an error naming the frame, `hold` keeps the last value and counts the miss.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from controllers.canbus import connection_closed
from controllers.curvature import CurvaturePI, PiGains
from controllers.kinematics import curvatures_from_markers
from controllers.protocol import (
    COUNTER_MODULO,
    CameraMarker,
    ControllerState,
    DriveCommand,
    DriveStatus,
    Emcy,
    FrameError,
    Heartbeat,
    Protocol,
    Sync,
)
from controllers.trajectories import CurvatureProfile, Sine

POLICIES = ("strict", "hold")


class ControllerError(RuntimeError):
    """The controller cannot go on; the message names the frame, cycle or peer."""


@dataclass(frozen=True)
class ControllerConfig:
    """Everything the controller knows about the rig and its task (written by `hil run`)."""

    lengths: tuple[float, ...]
    base: tuple[float, float, float]
    control_period: float
    cycles: int
    x_mid: float
    x_min: float
    x_max: float
    gains: PiGains
    profile: CurvatureProfile
    feedforward: float = 0.0  # piston offset per unit curvature reference [m per 1/m]
    policy: str = "strict"
    timeout: float = 10.0  # wall-clock wait for a cycle's frames [s]

    @property
    def segments(self) -> int:
        return len(self.lengths)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ControllerConfig:
        data: dict[str, Any] = json.loads(text)
        profile = data["profile"]
        sine = profile.get("sine")
        data["profile"] = CurvatureProfile(
            steps=tuple((float(t), float(k)) for t, k in profile["steps"]),
            sine=Sine(**sine) if sine else None,
            scale=tuple(profile["scale"]),
        )
        data["gains"] = PiGains(**data["gains"])
        data["lengths"] = tuple(data["lengths"])
        data["base"] = tuple(data["base"])
        return cls(**data)


@dataclass
class ControllerReport:
    """What the controller counted; written as JSON at the end of a run."""

    cycles: int = 0
    status_missed: int = 0
    stale_frames: int = 0
    unknown_frames: int = 0
    camera_frames: int = 0
    camera_frames_incomplete: int = 0
    emcy: list[dict[str, Any]] = field(default_factory=list)
    realtime: bool = False
    max_lateness: float = 0.0
    mean_lateness: float = 0.0
    overruns: int = 0
    frames_sent: int = 0
    frames_received: int = 0


class LockstepClock:
    """As fast as possible: the next SYNC goes out as soon as the cycle's work is done."""

    realtime = False

    def wait_for(self, cycle: int) -> float:
        return 0.0


class RealtimeClock:
    """SYNC(c) at wall-clock t0 + c T; returns the lateness of each SYNC [s]."""

    realtime = True

    def __init__(self, period: float) -> None:
        self.period = period
        self.start: float | None = None

    def wait_for(self, cycle: int) -> float:
        now = time.monotonic()
        if self.start is None:
            self.start = now
        deadline = self.start + cycle * self.period
        if deadline > now:
            time.sleep(deadline - now)
            now = time.monotonic()
        return max(0.0, now - deadline)


class CameraAssembler:
    """Groups marker frames by camera frame index and keeps the newest complete frame."""

    def __init__(self, markers: int) -> None:
        self.markers = markers
        self._pending: dict[int, dict[int, CameraMarker]] = {}
        self.latest: np.ndarray | None = None
        self.latest_exposure: float = -math.inf

    def add(self, marker: CameraMarker, sync_time: float) -> bool:
        """Add one marker; True when it completed a frame newer than the latest."""
        frame = self._pending.setdefault(marker.frame_index, {})
        frame[marker.marker_id] = marker
        if len(frame) < self.markers:
            return False
        del self._pending[marker.frame_index]
        exposure = sync_time - marker.exposure_offset
        if exposure <= self.latest_exposure:
            return False
        self.latest = np.array([[frame[m].x, frame[m].y] for m in range(self.markers)])
        self.latest_exposure = exposure
        return True

    def drop_incomplete(self) -> int:
        """Forget partial frames (a marker was lost); returns how many were dropped."""
        dropped = len(self._pending)
        self._pending.clear()
        return dropped


class ControllerNode:
    """The controller bound to a bus; `run()` drives the whole experiment."""

    def __init__(
        self,
        config: ControllerConfig,
        bus: can.BusABC,
        clock: LockstepClock | RealtimeClock | None = None,
        protocol: Protocol | None = None,
    ) -> None:
        if config.policy not in POLICIES:
            raise ControllerError(f"policy {config.policy!r}: must be one of {POLICIES}")
        self.config = config
        self.bus = bus
        self.clock = clock or LockstepClock()
        self.protocol = protocol or Protocol()
        self.state_kappa_range = self.protocol.signal_range("ControllerState1", "kappa_est")
        self.report = ControllerReport(realtime=self.clock.realtime)
        self.camera = CameraAssembler(config.segments + 1)
        self.controllers = [
            CurvaturePI(
                config.gains,
                config.control_period,
                config.x_mid,
                config.x_min,
                config.x_max,
                config.feedforward,
            )
            for _ in range(config.segments)
        ]
        self.kappa_est = np.zeros(config.segments)
        self.status: dict[int, DriveStatus] = {}

    def _send(self, frame: Sync | DriveCommand | ControllerState, sim_time: float) -> None:
        message = self.protocol.encode(frame, timestamp=sim_time)
        try:
            self.bus.send(message)
        except (OSError, can.CanError) as exc:
            raise ControllerError(
                f"sending {type(frame).__name__} at t = {sim_time:.3f} s: the bus is gone ({exc})"
            ) from exc
        self.report.frames_sent += 1

    def run(self) -> ControllerReport:
        """Run every cycle of the experiment; raises ControllerError under the strict policy."""
        T = self.config.control_period
        lateness = []
        for cycle in range(self.config.cycles + 1):
            lateness.append(self.clock.wait_for(cycle))
            t = cycle * T
            self._send(Sync(cycle), t)
            self._collect(cycle, t)
            self.report.cycles = cycle
            if cycle == self.config.cycles:
                break  # the final SYNC lets the plant reach the end time; nothing acts after it
            self._control(cycle, t)
        if lateness:
            self.report.max_lateness = max(lateness)
            self.report.mean_lateness = float(np.mean(lateness))
            self.report.overruns = sum(1 for late in lateness if late > T)
        return self.report

    def _collect(self, cycle: int, t: float) -> None:
        needed = set(range(1, self.config.segments + 1))
        deadline = time.monotonic() + self.config.timeout
        counter = cycle % COUNTER_MODULO
        while needed:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                missing = ", ".join(f"DriveStatus{n}" for n in sorted(needed))
                if self.config.policy == "strict":
                    raise ControllerError(
                        f"no {missing} for SYNC {cycle} (t = {t:.3f} s) within "
                        f"{self.config.timeout:g} s: is the plant running?"
                    )
                self.report.status_missed += len(needed)
                return
            message = self.bus.recv(timeout=min(remaining, 0.5))
            if message is None:
                if connection_closed(self.bus):
                    raise ControllerError(
                        f"the bus closed while waiting for SYNC {cycle}'s status: the plant "
                        "and its loopback hub are gone"
                    )
                continue
            self.report.frames_received += 1
            try:
                frame = self.protocol.decode(message)
            except FrameError as exc:
                if self.config.policy == "strict":
                    raise ControllerError(f"at SYNC {cycle}: {exc}") from exc
                self.report.unknown_frames += 1
                continue
            if isinstance(frame, DriveStatus):
                if frame.counter != counter or frame.node not in needed:
                    if self.config.policy == "strict":
                        raise ControllerError(
                            f"stale DriveStatus{frame.node} (counter {frame.counter}) while "
                            f"waiting for SYNC {cycle} (counter {counter})"
                        )
                    self.report.stale_frames += 1
                    continue
                self.status[frame.node] = frame
                needed.discard(frame.node)
            elif isinstance(frame, CameraMarker):
                if self.camera.add(frame, t):
                    self.report.camera_frames += 1
            elif isinstance(frame, Emcy):
                self.report.emcy.append({"cycle": cycle, **asdict(frame)})
            elif isinstance(frame, Heartbeat):
                continue
            elif self.config.policy == "strict":
                raise ControllerError(
                    f"unexpected {type(frame).__name__} at SYNC {cycle}: is another controller "
                    "on the bus?"
                )
        self.report.camera_frames_incomplete += self.camera.drop_incomplete()

    def _control(self, cycle: int, t: float) -> None:
        config = self.config
        if self.camera.latest is not None:
            self.kappa_est = curvatures_from_markers(
                self.camera.latest, config.lengths, config.base[2]
            )
        for i, pi in enumerate(self.controllers):
            node = i + 1
            kappa_ref = config.profile.for_segment(i, t)
            status = self.status.get(node)
            piston = status.piston_position if status is not None else None
            setpoint = pi.update(kappa_ref, float(self.kappa_est[i]), piston)
            self._send(DriveCommand(node, setpoint, True, cycle), t)
            # the state frame is for recording: an estimate beyond its range is shown saturated
            lo, hi = self.state_kappa_range
            shown = min(max(float(self.kappa_est[i]), lo), hi)
            self._send(ControllerState(node, kappa_ref, shown, cycle), t)


def write_report(report: ControllerReport, path: Path) -> None:
    path.write_text(json.dumps(asdict(report), indent=2, sort_keys=True) + "\n")
