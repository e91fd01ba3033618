"""The plant node: the simulated rig answering the controller's SYNC (docs/sync-cycle.md).

On SYNC(c) the plant
  1. advances the physics to t_c = c T with the commands that were active,
  2. lets every device node act from its inputs at t_c: latch the commands received since the
     previous SYNC (they act from this SYNC on), guard its own safety, and return its frames,
  3. sends every node's frames in phase order (emergencies, heartbeats, measurements such as
     camera frames, then status), nodes in rig order, then records the signals of t_c.
The plant knows no robot: the rig (FMUs, device nodes, connections, recorded signals) comes from
the robot kind. Everything it sends or receives is logged with simulation time; signals are
recorded at every SYNC. Nothing here depends on wall-clock time except the wait for a silent peer.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import can

from hil.cosim import Algorithm, Execution, StepAhead
from hil.cosim.execution import OVERLAP_MIN_COST
from hil.devices import DeviceNode, SyncContext
from hil.errors import BusError, FmuError, HilError, ProtocolError
from hil.recording import CanLogger, SignalRecorder
from hil.rig import Rig
from hil.scenario import Scenario
from rigbus.canbus import connection_closed, failure_text, send_all
from rigbus.heap import frozen_heap
from rigbus.protocol import (
    COUNTER_MODULO,
    EMCY_COMMAND_TIMEOUT,
    EMCY_OVER_PRESSURE,
    CameraFrame,
    CameraMarker,
    CameraMarker3D,
    DriveStatus,
    Emcy,
    Frame,
    FrameError,
    GenericFrame,
    Heartbeat,
    Protocol,
    Sync,
    frame_key,
    frame_signals,
)

# frames only the plant sends: on its bus they come from an intruder (no bus echoes own frames)
PLANT_FRAMES = (DriveStatus, CameraMarker, CameraMarker3D, CameraFrame, Emcy, Heartbeat)


class _Route(NamedTuple):
    """Where a received CAN id's frames go (`Plant._route`)."""

    plant_frame: bool  # a frame only the plant sends: from another node, an intrusion
    nodes: tuple[DeviceNode, ...]  # the device nodes that accept it
    recorded: tuple[tuple[str, str], ...]  # the rig's recorded signals of it: (signal, column)


STARTUP_TIMEOUT = 60.0  # [s] wall clock for the controller's first SYNC
EMCY_REASONS = {EMCY_OVER_PRESSURE: "over-pressure", EMCY_COMMAND_TIMEOUT: "command timeout"}


def when(reached: dict[str, float | int]) -> str:
    """Where a run is or stopped, for a message: before SYNC 0, or the time and the last SYNC
    ("at t = 1.230 s (after SYNC 123 of 1000)")."""
    if reached["cycle"] < 0:
        return "before SYNC 0"
    return f"at t = {reached['time']:.3f} s (after SYNC {reached['cycle']} of {reached['cycles']})"


@dataclass
class PlantStats:
    sync_received: int = 0
    commands_missed: int = 0
    commands_stale: int = 0
    unknown_frames: int = 0
    emcy_sent: int = 0
    setpoints_clamped: int = 0  # SYNCs at which a drive's servo had clamped its setpoint
    first_clamped: str = ""
    intrusions: int = 0  # frames that another node sent in a legitimate sender's name
    first_intrusion: str = ""
    wall_time: float = 0.0  # from the first SYNC to the last: the loop itself
    periods_on_thread: int = 0  # periods the FMUs stepped on the kernel's worker thread
    startup_time: float = 0.0  # from serving to the controller's first SYNC (its start-up)


class Plant:
    """The simulated rig on the bus; `run` serves SYNCs until the scenario's last cycle."""

    def __init__(
        self,
        scenario: Scenario,
        bus: can.BusABC,
        rig: Rig,
        signals: SignalRecorder,
        can_log: CanLogger,
        protocol: Protocol | None = None,
        heartbeat_every: int = 100,
    ) -> None:
        self.scenario = scenario
        self.bus = bus
        self.rig = rig
        self.algorithm = Algorithm(rig.participants, rig.connections, scenario.timing.step)
        # the step-ahead policy: IN_TURN serving a controller in another process (`run`),
        # AT_SYNC or WORKER for one in this thread (`run_driven`)
        self.execution = Execution(self.algorithm, scenario.control_ticks, scenario.cycles)
        self.signals = signals
        self.can_log = can_log
        self.protocol = protocol or Protocol()
        self.stats = PlantStats()
        self.nodes = rig.nodes
        # the recorded values, read at every SYNC in the recorder's order
        source_of = {s.column: s.source for s in rig.signals if s.source is not None}
        unknown = [c for c in signals.source_columns if c not in source_of]
        if unknown:
            raise HilError(f"{signals.path.name}: no source for column {unknown[0]!r} in the rig")
        self._sourced = self.algorithm.reader([source_of[c] for c in signals.source_columns])
        self.sim_time = 0.0
        self.cycle = -1
        self.heartbeat_every = heartbeat_every
        self._progress: Callable[[int], None] | None = None
        self._heard: set[tuple[int, int]] = set()  # (CAN id, counter) received this period
        self._routes: dict[int, _Route] = {}  # by CAN id (`_route`)

    def run(
        self,
        peer_alive: Callable[[], str | None],
        progress: Callable[[int], None] | None = None,
        startup_timeout: float | None = None,
    ) -> PlantStats:
        """Serve SYNC(0..cycles). `peer_alive` returns None while the controller lives, else why
        it is gone; a silent bus is checked against it and against the controller timeout
        (before the first SYNC: `startup_timeout` [s], by default STARTUP_TIMEOUT or the
        controller timeout if longer)."""
        started = time.perf_counter()
        last_heard = time.monotonic()
        final = self.scenario.cycles
        self.execution.policy = StepAhead.IN_TURN  # while the controller's process computes
        if startup_timeout is None:
            startup_timeout = max(STARTUP_TIMEOUT, self.scenario.controller.timeout)
        try:
            with frozen_heap():  # a full collection in the loop: only the loop's objects
                while self.cycle < final:
                    try:
                        message = self.bus.recv(timeout=0.1)
                    except (can.CanError, OSError) as exc:
                        raise BusError(
                            f"the bus failed {self._when()}: "
                            f"{failure_text(exc)}; is the loopback hub gone?"
                        ) from None
                    if message is None:
                        if connection_closed(self.bus):
                            raise BusError(f"the loopback hub closed the bus {self._when()}")
                        gone = peer_alive()
                        if gone is not None:
                            raise ProtocolError(f"{gone}; the plant stopped {self._when()}")
                        # a controller program still starting (imports on a loaded machine) gets
                        # startup_timeout for its first SYNC; after that the scenario's timeout
                        limit = self.scenario.controller.timeout
                        if self.cycle < 0:
                            limit = startup_timeout
                        if time.monotonic() - last_heard > limit:
                            if self.cycle < 0 and not self.stats.startup_time:
                                raise ProtocolError(
                                    f"no SYNC(0) from the controller within {limit:g} s of the "
                                    "start; the plant stopped"
                                )
                            raise ProtocolError(
                                f"no frame from the controller for {limit:g} s {self._when()}"
                            )
                        continue
                    last_heard = time.monotonic()
                    if self.cycle < 0 and not self.stats.startup_time:
                        first = time.perf_counter()
                        self.stats.startup_time = first - started
                        started = first
                    self._handle(message, progress)
        finally:
            self._count()
            self.stats.wall_time = time.perf_counter() - started
            self.signals.end_row()
            self.can_log.flush(force=True)
        return self.stats

    def _when(self) -> str:
        """Where the run is, for a message: before SYNC 0, or the time and the last SYNC."""
        return when(self.reached())

    def reached(self) -> dict[str, float | int]:
        """How far the run got (summary.json's `reached` of a run that stopped early): the
        simulation time [s], the last SYNC served (-1: none) and the run's final SYNC."""
        return {"time": self.sim_time, "cycle": self.cycle, "cycles": self.scenario.cycles}

    def run_driven(
        self,
        driver: Callable[[], object],
        progress: Callable[[int], None] | None = None,
        overlap: float | None = None,
        overlap_min_cost: float = OVERLAP_MIN_COST,
    ) -> PlantStats:
        """Serve a controller that drives the run from this thread (the direct in-process bus):
        each frame it sends reaches `handle` synchronously; `driver` returns when it is done.
        With `overlap` (seconds this thread polls for the worker before it sleeps) the FMUs step
        to the next SYNC on the kernel's worker thread while the controller computes in this
        one (`StepAhead.WORKER`: nothing changes by a bit), where a period costs at least
        `overlap_min_cost` [s] to step (0: always); without, at each SYNC (`AT_SYNC`)."""
        started = time.perf_counter()
        self._progress = progress
        execution = self.execution
        if overlap is not None:
            execution.policy, execution.spin = StepAhead.WORKER, overlap
            execution.min_cost = overlap_min_cost
        try:
            with frozen_heap():  # a full collection in the loop: only the loop's objects
                driver()
            if self.cycle < self.scenario.cycles:
                raise ProtocolError(
                    f"the controller stopped after SYNC {self.cycle} of {self.scenario.cycles}"
                )
        finally:
            try:
                execution.settle()  # no FMU steps on after the run, nor into a forked child
            finally:
                self.stats.periods_on_thread = execution.periods_on_thread
                self._count()
                self.stats.wall_time = time.perf_counter() - started
                self.signals.end_row()
                self.can_log.flush(force=True)
        return self.stats

    def handle(self, message: can.Message) -> None:
        """One frame from the bus (the direct bus's handler)."""
        self._handle(message, self._progress)

    def _decode(self, message: can.Message) -> Frame | None:
        try:
            return self.protocol.decode(message)
        except FrameError as exc:
            self.can_log.log(message, self.sim_time, received=True)
            if self.scenario.controller.policy == "strict":
                raise BusError(f"at t = {self.sim_time:.3f} s: {exc}") from exc
            self.stats.unknown_frames += 1
            return None

    def _handle(self, message: can.Message, progress: Callable[[int], None] | None) -> None:
        frame = self._decode(message)
        if frame is None:
            return
        if isinstance(frame, Sync):
            expected = (self.cycle + 1) % COUNTER_MODULO
            if frame.counter != expected:
                self.can_log.log(message, self.sim_time, received=True)
                self._intrusion(
                    f"SYNC counter {frame.counter} where {expected} was due "
                    f"(t = {self.sim_time:.3f} s): a SYNC was lost or another master is on the bus"
                )
                return
            self._heard.clear()
            self.cycle += 1
            # t = c T from the integer cycle, rounded: files show 3.53, not 3.5300000000000002
            self.sim_time = round(self.cycle * self.scenario.timing.control_period, 9)
            self.can_log.log(message, self.sim_time, received=True)
            self.stats.sync_received += 1
            self._on_sync(self.cycle)
            if progress is not None:
                progress(self.cycle)
            self.execution.after_sync(self.cycle)  # the step-ahead policy's work, if any
            return
        self.can_log.log(message, self.sim_time, received=True)
        route = self._routes.get(message.arbitration_id)
        if route is None:
            route = self._routes[message.arbitration_id] = self._route(frame)
        if route.plant_frame:
            self._intrusion(
                f"{type(frame).__name__} 0x{message.arbitration_id:03X} from another node at "
                f"t = {self.sim_time:.3f} s: only the plant sends it"
            )
            return
        counter = getattr(frame, "counter", None)
        if counter is not None:
            heard = (message.arbitration_id, counter)
            if heard in self._heard:
                self._intrusion(
                    f"a second {type(frame).__name__} 0x{message.arbitration_id:03X} with "
                    f"counter {counter} at t = {self.sim_time:.3f} s: another node sends in "
                    "the controller's name"
                )
                return
            self._heard.add(heard)
        for node in route.nodes:
            node.receive(frame)
        if route.recorded:
            if isinstance(frame, GenericFrame):
                cells = [(column, frame.signals[name]) for name, column in route.recorded]
            else:  # a typed frame: its signals are its fields
                cells = [(column, getattr(frame, name)) for name, column in route.recorded]
            self.signals.set_cells(cells)
        if route.nodes or route.recorded:
            return
        if self.scenario.controller.policy == "strict":
            raise BusError(
                f"at t = {self.sim_time:.3f} s: unexpected {type(frame).__name__} frame "
                f"0x{message.arbitration_id:03X} on the plant's bus"
            )
        self.stats.unknown_frames += 1

    def _intrusion(self, what: str) -> None:
        """A frame its one legitimate sender did not send: counted (the first one described);
        under the strict policy the run stops."""
        if self.scenario.controller.policy == "strict":
            raise ProtocolError(f"intrusion on the bus: {what}")
        self.stats.intrusions += 1
        if not self.stats.first_intrusion:
            self.stats.first_intrusion = what

    def _route(self, frame: Frame) -> _Route:
        """Where the frames of `frame`'s CAN id go: a CAN id always decodes to the same kind
        and index, and a node accepts by those (`DeviceNode.accepts`), as a CAN controller's
        acceptance filter does, so this is found once per id."""
        kind, index = frame_key(frame)
        return _Route(
            isinstance(frame, PLANT_FRAMES),
            tuple(node for node in self.nodes if node.accepts(frame)),
            # what the controller reports about itself that the rig records (its
            # frame-sourced signals; most frames, none): the columns of the frame's signals
            tuple(
                (name, column)
                for name, column in self.signals.frame_columns(kind, index)
                if name in frame_signals(frame)
            ),
        )

    def _send(self, frames: list[Frame]) -> None:
        """Encode a SYNC's frames and send them in order, in one write where the bus can
        (`send_all`), then log them."""
        at = self.sim_time
        messages = []
        for frame in frames:
            try:
                messages.append(self.protocol.encode(frame, timestamp=at))
            except FrameError as exc:
                raise BusError(f"at t = {at:.3f} s: {exc}") from exc
        try:
            send_all(self.bus, messages)
        except (can.CanError, OSError) as exc:
            ids = ", ".join(f"0x{m.arbitration_id:03X}" for m in messages)
            raise BusError(f"sending {ids}: {exc}") from exc
        self.can_log.log_all(messages, at, received=False)

    def _on_sync(self, cycle: int) -> None:
        try:
            self.execution.to_sync(cycle)
        except FmuError as exc:
            raise FmuError(f"at t = {self.sim_time:.3f} s: {exc}") from exc
        algorithm = self.algorithm
        sync_tick = cycle * self.scenario.control_ticks
        sync = SyncContext(cycle, sync_tick, self.sim_time, cycle % self.heartbeat_every == 0)
        outgoing: list[tuple[int, Frame]] = []
        for node in self.nodes:
            outgoing += node.act(sync, algorithm.inputs_of(node.name))
            algorithm.publish(node.name)
        outgoing.sort(key=lambda phase_frame: phase_frame[0])  # stable: rig order within a phase
        try:
            self._send([frame for _, frame in outgoing])
        finally:
            # the row of this SYNC (writing the last one) once its frames are out, so the
            # controller is not kept waiting for the CSV; the values are the SYNC's still (the
            # master steps on after this); a failed send still records the row
            self.signals.begin_row(self.sim_time, self._sourced())
        self.can_log.flush()
        if self.scenario.controller.policy == "strict":
            self._strict(outgoing)

    def _at(self) -> str:
        """The SYNC and time, for a message."""
        return f"at SYNC {self.cycle} (t = {self.sim_time:.3f} s)"

    def _count(self) -> None:
        """The device nodes' counts into the stats: when the run ends, however it ends."""
        stats = self.stats
        stats.commands_missed = sum(getattr(n, "missed", 0) for n in self.nodes)
        stats.commands_stale = sum(getattr(n, "stale", 0) for n in self.nodes)
        stats.emcy_sent = sum(getattr(n, "emcy_sent", 0) for n in self.nodes)
        stats.setpoints_clamped = sum(getattr(n, "clamped", 0) for n in self.nodes)
        if stats.setpoints_clamped and not stats.first_clamped:
            firsts = [
                (first, n.name) for n in self.nodes if (first := getattr(n, "first_clamped", None))
            ]  # the earliest; at one SYNC, the first node
            (at, setpoint), name = min(firsts, key=lambda pair: pair[0][0])
            stats.first_clamped = f"{name} at t = {at:.3f} s, setpoint {setpoint:.6g} m"

    def _strict(self, sent: list[tuple[int, Frame]]) -> None:
        """Under the strict policy a missed or stale command, or an EMCY, ends the run (the
        stats are counted as it ends, `_count`)."""
        for _, frame in sent:
            if isinstance(frame, Emcy):
                raise ProtocolError(
                    f"EMCY 0x{frame.error_code:04X} ({EMCY_REASONS.get(frame.error_code, 'fault')})"
                    f" from drive {frame.node} {self._at()}; the strict policy stops the run"
                )
        missed = stale = 0
        for node in self.nodes:
            missed += getattr(node, "missed", 0)
            stale += getattr(node, "stale", 0)
        if missed or stale:
            what = "missed" if missed else "stale"
            at = self._at()
            raise ProtocolError(
                f"a drive command was {what} {at}: the controller did not command the last "
                "period; the strict policy stops the run"
            )
