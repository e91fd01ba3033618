"""The controller node: a separate program that sees the rig only through the CAN bus.

It is the SYNC producer (as a CANopen master on a rig). Cycle c:
  1. wait for the period (real-time clock) or not at all (lockstep), send SYNC(c);
  2. collect what cycle c must bring, known from the frames themselves and the devices'
     announced rates, never from the order in which they arrive (on a real bus the lower ids win
     arbitration): every drive's status frame echoing c, and every camera frame whose exposure
     plus latency falls at or before this SYNC (partial camera frames are kept until complete);
  3. hand the cycle's drive readings and completed camera frames to the robot's `Estimator`,
     the estimate to the robot's `Controller`, and send the frames it returns;
then SYNC(c+1). Commands computed from the status of c act from SYNC(c+1): one control period of
computation delay, as on a rig. Missing or stale frames follow the policy: `strict` stops with an
error naming the frame, `hold` keeps the last value and counts the miss.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from controllers.config import POLICIES
from controllers.estimation import (
    Controller,
    Estimator,
    MarkerFrame,
)
from rigbus.canbus import connection_closed, failure_text, send_all
from rigbus.heap import frozen_heap
from rigbus.protocol import (
    COUNTER_MODULO,
    CameraFrame,
    CameraMarker,
    CameraMarker3D,
    ControllerState,
    DriveCommand,
    Emcy,
    FrameError,
    GenericFrame,
    Heartbeat,
    Protocol,
    SpatialTaskState,
    Sync,
    TaskState,
    frame_key,
)
from rigbus.robots import controller_side

OWN_FRAMES = (
    Sync,
    DriveCommand,
    ControllerState,
    TaskState,
    SpatialTaskState,
)  # the frames only the controller sends
OWN_KINDS = ("ValveCommand", "FishState")  # and those of kinds with no registered type

# a frame's kind and index: ("DriveStatus", 3), ("CanisterStatus", None)
_Key = tuple[str, int | None]
# what `ControllerNode._collect` does with a frame of one route (`ControllerNode._on_status` ...):
# called with the frame, its kind and index, its message, the cycle, the status frames the cycle
# still needs
_Handler = Callable[[Any, _Key, can.Message, int, set[_Key]], None]


class ControllerError(RuntimeError):
    """The controller cannot go on; the message names the frame, cycle or peer."""


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
    intrusions: int = 0  # frames in the controller's (or a drive's) name that it did not send
    first_intrusion: str = ""
    notes: list[str] = field(default_factory=list)  # what the task wants told (summary warnings)


class LockstepClock:
    """As fast as possible: the next SYNC goes out as soon as the cycle's work is done."""

    realtime = False

    def wait_for(self, cycle: int) -> float:
        return 0.0


class RealtimeClock:
    """SYNC(c) at wall-clock t0 + c T; returns the lateness of each SYNC [s]. `sleep` and
    `monotonic` are injectable so the pacing can be tested without waiting."""

    realtime = True

    def __init__(
        self,
        period: float,
        sleep: Callable[[float], None] = time.sleep,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.period = period
        self.start: float | None = None
        self._sleep = sleep
        self._monotonic = monotonic

    def wait_for(self, cycle: int) -> float:
        now = self._monotonic()
        if self.start is None:
            self.start = now
        deadline = self.start + cycle * self.period
        if deadline > now:
            self._sleep(deadline - now)
            now = self._monotonic()
        return max(0.0, now - deadline)


class CameraAssembler:
    """Collects each camera picture: its CameraFrame header says which markers it holds; the
    picture is complete when all of them have arrived, in whatever order."""

    def __init__(self, markers: int, dims: int = 2) -> None:
        self.markers = markers
        self.dims = dims  # 2: CameraMarker frames (x, y); 3: CameraMarker3D (x, y, z)
        self._unseen = (math.nan,) * dims
        self._all_markers = (1 << markers) - 1  # the mask bits of markers 0 .. markers - 1
        self._headers: dict[int, CameraFrame] = {}
        # each picture's markers by id, as (x, y) or (x, y, z) rows
        self._pending: dict[int, dict[int, tuple[float, ...]]] = {}

    def add(self, frame: CameraFrame | CameraMarker | CameraMarker3D) -> None:
        if isinstance(frame, CameraFrame):
            self._headers[frame.frame_index] = frame
        elif 0 <= frame.marker_id < self.markers:
            row = (
                (frame.x, frame.y)
                if isinstance(frame, CameraMarker)
                else (frame.x, frame.y, frame.z)
            )
            if len(row) == self.dims:  # a marker of the other kind is not this camera's
                self._pending.setdefault(frame.frame_index, {})[frame.marker_id] = row

    def complete(self, index: int) -> bool:
        header = self._headers.get(index % COUNTER_MODULO)
        if header is None:
            return False
        have = self._pending.get(index % COUNTER_MODULO, {})
        mask = header.marker_mask & self._all_markers
        # asked after every frame of a picture: fewer markers in than it holds is the usual
        # answer, found without the look-ups
        if len(have) < mask.bit_count():
            return False
        return all(m in have for m in range(self.markers) if mask >> m & 1)

    def take(self, index: int, sync_time: float) -> MarkerFrame:
        """The picture `index` (complete) stamped with its exposure time; markers it does not
        hold are NaN."""
        key = index % COUNTER_MODULO
        header = self._headers.pop(key)
        frame = self._pending.pop(key, {})
        # the rows as floats, one array made of them (not a row assignment per marker)
        rows: list[tuple[float, ...]] = [self._unseen] * self.markers
        for m, row in frame.items():
            if header.marker_mask >> m & 1:
                rows[m] = row
        points = np.array(rows, dtype=float)
        return MarkerFrame(exposure_time=sync_time - header.exposure_offset, points=points)

    def drop(self, index: int) -> bool:
        """Forget a picture that will not complete; True if part of it had arrived."""
        key = index % COUNTER_MODULO
        had = key in self._headers or key in self._pending
        self._headers.pop(key, None)
        self._pending.pop(key, None)
        return had


class ControllerNode:
    """The controller bound to a bus; `run()` drives the whole experiment."""

    def __init__(
        self,
        config: Any,
        bus: can.BusABC,
        clock: LockstepClock | RealtimeClock | None = None,
        protocol: Protocol | None = None,
        estimator: Estimator | None = None,
        controller: Controller | None = None,
    ) -> None:
        if config.policy not in POLICIES:
            raise ControllerError(f"policy {config.policy!r}: must be one of {POLICIES}")
        module = controller_side(config.robot)

        self.config = config
        self.module = module
        self.bus = bus
        self.clock = clock or LockstepClock()
        self.protocol = protocol or Protocol()
        self.report = ControllerReport(realtime=self.clock.realtime)
        self.camera = CameraAssembler(config.camera_timing.markers, config.camera_timing.dims)
        self.estimator = estimator or module.make_estimator(config)
        self.controller = controller or module.make_controller(config, self.protocol)
        self.expected: set[tuple[str, int | None]] = module.expected(config)
        self.status: dict[tuple[str, int | None], Any] = {}
        self._status_kinds = {kind for kind, _ in self.expected}
        self._frames_taken = 0  # camera frames 0 .. _frames_taken - 1 are done with
        self._outbox: list[can.Message] = []  # encoded, not yet sent (`_flush`)
        self._outbox_time = 0.0
        # what `_collect` does with a frame, by its route (`_route`), and by CAN id
        self._handlers: dict[str, _Handler] = {
            _STATUS: self._on_status,
            _CAMERA: self._on_camera,
            _EMCY: self._on_emcy,
            _HEARTBEAT: self._on_heartbeat,
            _OWN: self._on_own,
            _OTHER: self._on_other,
        }
        self._routes: dict[int, tuple[_Handler, _Key]] = {}

    def _send(self, frame: Any, sim_time: float) -> None:
        """Queue one frame; `_flush` sends the queue in order."""
        self._outbox.append(self.protocol.encode(frame, timestamp=sim_time))
        self._outbox_time = sim_time

    def _flush(self) -> None:
        """Send the queued frames in order, in one write where the bus can (`send_all`)."""
        messages, self._outbox = self._outbox, []
        if not messages:
            return
        try:
            send_all(self.bus, messages)
        except (OSError, can.CanError) as exc:
            ids = ", ".join(f"0x{m.arbitration_id:03X}" for m in messages)
            raise ControllerError(
                f"sending {ids} at t = {self._outbox_time:.3f} s: the bus is gone ({exc})"
            ) from exc
        self.report.frames_sent += len(messages)

    def run(self) -> ControllerReport:
        """Run every cycle of the experiment; raises ControllerError under the strict policy.
        In lockstep on a bus that sends batches (softhil's binary records), a cycle's commands
        go out with the next SYNC, in one write: nothing can tell the difference (the plant
        latches commands at SYNC, and the order of frames is the same), and it halves the
        writes and hub wake-ups per cycle. Otherwise (the real-time clock, as on a rig; other
        buses, where it would save nothing) they go out as soon as they are computed."""
        T = self.config.control_period
        lateness: list[float] = []
        batching = not self.clock.realtime and hasattr(self.bus, "send_batch")
        with frozen_heap():  # a full collection in the loop: only the loop's objects
            self._cycles(lateness, batching)
        self.report.notes = [str(n) for n in getattr(self.controller, "notes", ())]
        if lateness:
            self.report.max_lateness = max(lateness)
            self.report.mean_lateness = float(np.mean(lateness))
            self.report.overruns = sum(1 for late in lateness if late > T)
        return self.report

    def _cycles(self, lateness: list[float], batching: bool) -> None:
        """Every cycle of `run`, each one's lateness appended to `lateness`."""
        T = self.config.control_period
        for cycle in range(self.config.cycles + 1):
            lateness.append(self.clock.wait_for(cycle))
            t = cycle * T
            self._send(Sync(cycle), t)
            self._flush()
            frames = self._collect(cycle, t)
            self.report.cycles = cycle
            if cycle == self.config.cycles:
                break  # the final SYNC lets the plant reach the end time; nothing acts after it
            readings = self.module.readings(self.status)
            estimate = self.estimator.update(t, readings, frames)
            for frame in self.controller.compute(cycle, t, estimate, readings):
                self._send(frame, t)
            if not batching:
                self._flush()

    def _intrusion(self, what: str) -> None:
        """Count a frame that its one legitimate sender did not send; strict stops."""
        if self.config.policy == "strict":
            raise ControllerError(f"intrusion on the bus: {what}")
        self.report.intrusions += 1
        if not self.report.first_intrusion:
            self.report.first_intrusion = what

    def _route(self, frame: Any) -> tuple[str, tuple[str, int | None]]:
        """What `_collect` does with the frames of `frame`'s CAN id (a CAN id always decodes
        to the same kind and index, so this is found once per id), and their (kind, index)."""
        key = frame_key(frame)
        if key[0] in self._status_kinds:
            return _STATUS, key
        if isinstance(frame, CameraMarker | CameraMarker3D | CameraFrame):
            return _CAMERA, key
        if isinstance(frame, Emcy):
            return _EMCY, key
        if isinstance(frame, Heartbeat):
            return _HEARTBEAT, key
        if isinstance(frame, OWN_FRAMES) or (
            isinstance(frame, GenericFrame) and frame.kind in OWN_KINDS
        ):
            return _OWN, key
        return _OTHER, key

    def _collect(self, cycle: int, t: float) -> list[MarkerFrame]:
        """Receive until the cycle holds every status frame echoing it and every camera frame
        due by this SYNC; returns the camera frames completed, oldest first."""
        needed = set(self.expected)
        due = self.config.camera_timing.frames_due(cycle)
        deadline = time.monotonic() + self.config.timeout
        while needed or not self._camera_complete(due):
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                self._missed(cycle, t, needed, due)
                break
            received = self._receive(cycle, remaining)
            if received is None:
                continue
            message, frame = received
            route = self._routes.get(message.arbitration_id)
            if route is None:
                what, key = self._route(frame)
                route = self._routes[message.arbitration_id] = (self._handlers[what], key)
            handle, key = route
            handle(frame, key, message, cycle, needed)
        return self._take_camera_frames(due, t)

    def _camera_complete(self, due: int) -> bool:
        """Whether every camera frame not yet taken, up to `due`, is complete."""
        return all(self.camera.complete(j) for j in range(self._frames_taken, due))

    def _missed(self, cycle: int, t: float, needed: set[_Key], due: int) -> None:
        """The cycle's wait ran out with frames `needed` and camera frames still missing: strict
        stops naming them, hold counts the status frames missed."""
        config = self.config
        missing = [_name(key) for key in sorted(needed, key=_name)]
        missing += [
            f"camera frame {j}"
            for j in range(self._frames_taken, due)
            if not self.camera.complete(j)
        ]
        if config.policy == "strict":
            raise ControllerError(
                f"no {', '.join(missing)} for SYNC {cycle} (t = {t:.3f} s) within "
                f"{config.timeout:g} s: is the plant running?"
            )
        self.report.status_missed += len(needed)

    def _receive(self, cycle: int, remaining: float) -> tuple[can.Message, Any] | None:
        """The next frame from the bus and its message, waiting at most `remaining` seconds
        (and half a second at a time); None if none came or (hold) it did not decode."""
        try:
            message = self.bus.recv(timeout=min(remaining, 0.5))
        except (can.CanError, OSError) as exc:
            raise ControllerError(
                f"the bus failed while waiting for SYNC {cycle}'s status "
                f"({failure_text(exc)}): the plant and its hub are gone?"
            ) from None
        if message is None:
            if connection_closed(self.bus):
                raise ControllerError(
                    f"the bus closed while waiting for SYNC {cycle}'s status: the plant "
                    "and its loopback hub are gone"
                )
            return None
        self.report.frames_received += 1
        try:
            return message, self.protocol.decode(message)
        except FrameError as exc:
            if self.config.policy == "strict":
                raise ControllerError(f"at SYNC {cycle}: {exc}") from exc
            self.report.unknown_frames += 1
            return None

    # what `_collect` does with each route's frames (`_route`, `_handlers`)

    def _on_status(
        self, frame: Any, key: _Key, message: can.Message, cycle: int, needed: set[_Key]
    ) -> None:
        """A status frame: the cycle's if it echoes it and is still needed; a second one is an
        intrusion, an old one stale."""
        counter = cycle % COUNTER_MODULO
        # the echoed counter, without building every signal's value (frame_signals)
        echo = int(frame.signals["counter"] if isinstance(frame, GenericFrame) else frame.counter)
        if echo == counter and key not in needed:
            self._intrusion(
                f"a second {_name(key)} for SYNC {cycle}: another node "
                f"sends in the {_SENDER.get(key[0], 'device')}'s name"
            )
            return
        if echo != counter or key not in needed:
            if self.config.policy == "strict":
                raise ControllerError(
                    f"stale {_name(key)} (counter {echo}) while "
                    f"waiting for SYNC {cycle} (counter {counter})"
                )
            self.report.stale_frames += 1
            return
        self.status[key] = frame
        needed.discard(key)

    def _on_camera(
        self, frame: Any, key: _Key, message: can.Message, cycle: int, needed: set[_Key]
    ) -> None:
        self.camera.add(frame)

    def _on_emcy(
        self, frame: Any, key: _Key, message: can.Message, cycle: int, needed: set[_Key]
    ) -> None:
        self.report.emcy.append({"cycle": cycle, **asdict(frame)})

    def _on_heartbeat(
        self, frame: Any, key: _Key, message: can.Message, cycle: int, needed: set[_Key]
    ) -> None:
        """Heartbeats are not watched here: a silent drive shows as its missing status."""

    def _on_own(
        self, frame: Any, key: _Key, message: can.Message, cycle: int, needed: set[_Key]
    ) -> None:
        # no bus echoes a sender's own frames: these come from another node
        self._intrusion(
            f"{type(frame).__name__} 0x{message.arbitration_id:03X} at SYNC {cycle} from "
            "another node: only this controller sends it"
        )

    def _on_other(
        self, frame: Any, key: _Key, message: can.Message, cycle: int, needed: set[_Key]
    ) -> None:
        if self.config.policy == "strict":
            raise ControllerError(
                f"unexpected {type(frame).__name__} at SYNC {cycle}: is another controller "
                "on the bus?"
            )
        self.report.unknown_frames += 1

    def _take_camera_frames(self, due: int, t: float) -> list[MarkerFrame]:
        """The camera frames due by this SYNC that are complete, oldest first; the incomplete
        ones are dropped and counted."""
        frames = []
        for j in range(self._frames_taken, due):
            if self.camera.complete(j):
                frames.append(self.camera.take(j, t))
                self.report.camera_frames += 1
            elif self.camera.drop(j):
                self.report.camera_frames_incomplete += 1
        self._frames_taken = max(self._frames_taken, due)
        return frames


# what `_collect` does with a received frame (`ControllerNode._route`)
_STATUS, _CAMERA, _EMCY, _HEARTBEAT, _OWN, _OTHER = (
    "status",
    "camera",
    "emcy",
    "heartbeat",
    "own",
    "other",
)
_SENDER = {"DriveStatus": "drive", "ValveStatus": "valve", "CanisterStatus": "canister"}


def _name(key: _Key) -> str:
    """The DBC message name of (kind, index): DriveStatus3, CanisterStatus."""
    return f"{key[0]}{'' if key[1] is None else key[1]}"


def write_report(report: ControllerReport, path: Path) -> None:
    path.write_text(json.dumps(asdict(report), indent=2, sort_keys=True) + "\n")
