"""CAN-log replay: a recorded run becomes a regression test for a controller.

A softhil CAN log holds both sides of every cycle, seen from the plant: after the SYNC(c) that
the controller sent (R), the frames the plant answered with (T: status, camera, EMCY,
heartbeat), then the frames the controller sent in answer to cycle c (R: commands, controller
state). `replay` plays the plant's side back to a controller node that runs unchanged (in this
process on a virtual bus, or as the separate `python -m controllers` program over a loopback hub)
and compares, signal by signal, what the controller sends with what was recorded. The log is
read as its cycles by `hil.cycles`.

The controller never knows: it sees the same frames, keyed by the SYNC counter it produces, as it
did in the run. With an unchanged controller the comparison is exact; a changed gain shows as
the first diverging cycle, message and signal.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import subprocess
import tempfile
import threading
import time
import uuid
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from hil.bustools.logs import has_direction
from hil.cycles import CSV_HAS_NO_DIRECTION, Cycle, config_beside, read_cycles, read_log
from hil.errors import HilError, ReplayError
from hil.program import SOFTHIL, USER_LINGER, check_controller, last_words, start, stop
from hil.seam import ControllerNode
from rigbus.canbus import BusSpec, open_bus
from rigbus.protocol import COUNTER_MODULO, SYNC_ID, Protocol
from rigbus.robots import RobotConfig

WAIT = 60.0  # s for the controller's SYNC(0), as `hil run --wait`: a program may load slowly
MAX_WAIT = 86400.0


@dataclass(frozen=True)
class Divergence:
    cycle: int
    time: float
    message: str
    signal: str
    expected: float | None  # None: the frame was not recorded / not sent
    actual: float | None

    def __str__(self) -> str:
        def shown(v: float | None) -> str:
            return "(no frame)" if v is None else f"{v:.9g}"

        return (
            f"cycle {self.cycle} (t = {self.time:.3f} s): {self.message}.{self.signal} "
            f"expected {shown(self.expected)}, got {shown(self.actual)}"
        )


@dataclass
class ReplayResult:
    cycles: int
    frames_compared: int
    divergences: list[Divergence] = field(default_factory=list)
    by_signal: dict[str, int] = field(default_factory=dict)
    # per cycle, the frames the controller sent in answer to its SYNC, in the order sent: what
    # was compared, for a check of the bytes (bits no signal covers) and of the order
    sent: list[list[can.Message]] = field(default_factory=list, repr=False)

    @property
    def ok(self) -> bool:
        return not self.divergences

    def summary(self) -> dict[str, Any]:
        return {
            "cycles": self.cycles,
            "frames_compared": self.frames_compared,
            "divergences": len(self.divergences),
            "first": str(self.divergences[0]) if self.divergences else None,
            "by_signal": dict(sorted(self.by_signal.items())),
        }


def check_served(cycles: Sequence[Cycle], config: Any, protocol: Protocol, source: str) -> None:
    """Under the strict policy softhil's controller stops at the first cycle that lacks a
    status frame echoing its SYNC or a camera picture due by it (after waiting its timeout, and
    asking whether the plant runs): say so before the replay starts, naming the cycle and the
    frame, and whether the log lacks it there (frames missing) or everywhere (the log of another
    robot than the controller's configuration)."""
    if getattr(config, "policy", "strict") != "strict":
        return  # `hold` goes on past a missing frame, as it did in the run
    from hil.seam import CameraAssembler
    from rigbus.protocol import CameraFrame, CameraMarker, GenericFrame, frame_key
    from rigbus.robots import controller_side

    expected = controller_side(config.robot).expected(config)
    kinds = {kind for kind, _ in expected}
    timing = config.camera_timing
    camera = CameraAssembler(timing.markers)
    seen: set[str] = set()  # the status frames the log holds anywhere, and "camera frames"
    taken = 0
    for cycle in cycles:
        have: set[tuple[str, int | None]] = set()
        for message in cycle.plant:
            frame = protocol.decode(message)  # read_cycles decoded every frame already
            key = frame_key(frame)
            if key[0] in kinds:
                seen.add(_name(key))
                echo = (
                    frame.signals["counter"] if isinstance(frame, GenericFrame) else frame.counter
                )
                if int(echo) == cycle.index % COUNTER_MODULO:
                    have.add(key)
            elif isinstance(frame, CameraFrame | CameraMarker):
                seen.add("camera frames")
                camera.add(frame)
        missing = [_name(key) for key in sorted(expected - have, key=_order)]
        due = timing.frames_due(cycle.index)
        pictures = [f"camera frame {j}" for j in range(taken, due) if not camera.complete(j)]
        for j in range(taken, due):
            camera.drop(j)
        taken = max(taken, due)
        if not missing and not pictures:
            continue
        nowhere = [name for name in missing if name not in seen]
        if pictures and "camera frames" not in seen:
            nowhere.append("camera frames")
        why = (
            f"the log holds no {nowhere[0]} at all: the log of another robot than the "
            "controller's (its controller.json or --scenario)?"
            if nowhere
            else "frames missing from the log?"
        )
        raise ReplayError(
            f"{source}: cycle {cycle.index} (t = {cycle.time:.3f} s) lacks "
            f"{', '.join(missing + pictures)}, which softhil's controller waits for at SYNC "
            f"{cycle.index} under its strict policy: {why}"
        )


def _name(key: tuple[str, int | None]) -> str:
    """The DBC message name of (kind, index): DriveStatus3, CanisterStatus."""
    return f"{key[0]}{'' if key[1] is None else key[1]}"


def _order(key: tuple[str, int | None]) -> tuple[str, int]:
    return key[0], -1 if key[1] is None else key[1]


class _ReplayPlant:
    """Answers the controller's SYNCs with the recorded plant frames; collects its answers."""

    def __init__(
        self,
        cycles: Sequence[Cycle],
        bus: can.BusABC,
        timeout: float,
        linger: float | None = None,
        wait: float | None = None,
    ) -> None:
        self.cycles = cycles
        self.bus = bus
        self.timeout = timeout
        self.wait = timeout if wait is None else wait  # for SYNC(0): a program starting up
        # after the final SYNC: how long a controller that is still there may stay silent
        # before the replay ends (frames it sends until then are compared)
        self.linger = timeout if linger is None else min(linger, timeout)
        self.sent: list[list[can.Message]] = [[] for _ in cycles]

    def _when(self, current: int) -> str:
        """Where the replay is, for a message: before SYNC 0, or the last cycle served."""
        if current < 0:
            return "before SYNC 0"
        return f"at cycle {current} of {len(self.cycles) - 1}"

    def run(self, alive: Any) -> None:
        current = -1
        last_heard = time.monotonic()
        final = len(self.cycles) - 1
        while True:
            message = self.bus.recv(timeout=0.05)
            if message is None:
                gone = alive()
                if gone is not None:
                    if current >= final:
                        return
                    raise ReplayError(f"{gone}; the replay stopped {self._when(current)}")
                silent = time.monotonic() - last_heard
                if current >= final and silent > self.linger:
                    return
                if current < 0 and silent > self.wait:
                    raise ReplayError(
                        f"no SYNC(0) from the controller within {self.wait:g} s of the start; "
                        "the replay stopped"
                    )
                if current >= 0 and silent > self.timeout:
                    raise ReplayError(
                        f"the controller sent nothing for {self.timeout:g} s {self._when(current)}"
                    )
                continue
            last_heard = time.monotonic()
            if message.arbitration_id == SYNC_ID:
                current += 1
                if current > final:
                    raise ReplayError(f"the controller went on past the log's last cycle {final}")
                for frame in self.cycles[current].plant:
                    self.bus.send(
                        can.Message(
                            arbitration_id=frame.arbitration_id,
                            data=bytes(frame.data),
                            is_extended_id=frame.is_extended_id,
                        )
                    )
                continue
            if current >= 0:
                self.sent[current].append(message)


def compare(
    cycles: Sequence[Cycle],
    sent: Sequence[Sequence[can.Message]],
    protocol: Protocol,
    tolerance: float = 0.0,
    tolerances: Mapping[str, float] | None = None,
) -> ReplayResult:
    """Signal-by-signal comparison of what the controller sent with what was recorded."""
    result = ReplayResult(
        cycles=len(cycles), frames_compared=0, sent=[list(frames) for frames in sent]
    )
    comparison = _Comparison(protocol, tolerance, tolerances or {}, result)
    for cycle, actual in zip(cycles, sent, strict=True):
        comparison.cycle(cycle, actual)
    return result


# a frame as `_by_name` gives it: its signals, the length it came with if that is not the
# DBC's, or None where no such frame was recorded or sent
_Frame = dict[str, float] | int | None


@dataclass(frozen=True)
class _Comparison:
    """A comparison's protocol and tolerances, and the result it fills."""

    protocol: Protocol
    tolerance: float
    tolerances: Mapping[str, float]
    result: ReplayResult

    def cycle(self, cycle: Cycle, actual: Sequence[can.Message]) -> None:
        """Compare what the controller sent in answer to `cycle` with what was recorded, frame
        by frame in the order of their CAN ids (then names)."""
        expected_frames, expected_count = _by_name(cycle.controller, self.protocol)
        actual_frames, actual_count = _by_name(actual, self.protocol)
        order = {
            name: can_id for name, (can_id, _) in (*expected_frames.items(), *actual_frames.items())
        }
        for name in sorted(order, key=lambda n: (order[n], n)):
            exp = expected_frames[name][1] if name in expected_frames else None
            act = actual_frames[name][1] if name in actual_frames else None
            counts = expected_count.get(name, 0), actual_count.get(name, 0)
            self.frame(cycle, name, order[name], exp, act, counts)

    def frame(
        self,
        cycle: Cycle,
        name: str,
        can_id: int,
        exp: _Frame,
        act: _Frame,
        counts: tuple[int, int],
    ) -> None:
        """Compare one frame of a cycle: how often it was sent, its length, whether it was
        sent at all, then each signal within its tolerance (NaN matches NaN)."""

        def note(signal: str, expected: float | None, actual: float | None) -> None:
            divergence = Divergence(cycle.index, cycle.time, name, signal, expected, actual)
            self.result.divergences.append(divergence)
            key = f"{name}.{signal}"
            self.result.by_signal[key] = self.result.by_signal.get(key, 0) + 1

        if exp is not None and act is not None and counts[0] != counts[1]:  # sent twice
            note("(count)", *map(float, counts))
        if isinstance(act, int) or isinstance(exp, int):  # the wrong length for the DBC
            length = self.protocol.message(can_id).length
            sizes = [v if isinstance(v, int) else length for v in (exp, act)]
            note("(length)", *sizes)
            return
        if exp is None or act is None:
            note("(frame)", None if exp is None else 1.0, None if act is None else 1.0)
            return
        self.result.frames_compared += 1
        for signal, e in exp.items():
            a = act[signal]
            limit = self.tolerances.get(
                signal, self.tolerances.get(f"{name}.{signal}", self.tolerance)
            )
            if not (abs(a - e) <= limit or (math.isnan(a) and math.isnan(e))):
                note(signal, e, a)


def check_tolerances(protocol: Protocol, tolerances: Mapping[str, float]) -> None:
    """Refuse a tolerance for a signal the DBC does not have (SIGNAL or MESSAGE.SIGNAL): a
    misspelt name would otherwise leave the signal at the default tolerance, silently."""
    known = {
        name
        for message in protocol.database.messages
        for signal in message.signals
        for name in (signal.name, f"{message.name}.{signal.name}")
    }
    for name in tolerances:
        if name not in known:
            raise ReplayError(
                f"tolerance for {name!r}: no such signal in {protocol.path.name} "
                "(name one as SIGNAL or MESSAGE.SIGNAL, e.g. DriveCommand1.piston_setpoint)"
            )


def _by_name(
    messages: Iterable[can.Message], protocol: Protocol
) -> tuple[dict[str, tuple[int, dict[str, float] | int]], dict[str, int]]:
    """Per frame name: (its id, its signals) of the last such frame, or for a DBC message of
    the wrong length (its id, the length it came with); an id the DBC lacks is named
    "0x123 (not in the DBC)" (an extended one "0x00000201 (extended, not in the DBC)"), with no
    signals. And how many frames of each name there were."""
    frames: dict[str, tuple[int, dict[str, float] | int]] = {}
    counts: dict[str, int] = {}
    known = {m.frame_id for m in protocol.database.messages}
    for message in messages:
        can_id, data = message.arbitration_id, bytes(message.data)
        if message.is_extended_id or can_id not in known:
            name = (
                f"0x{can_id:08X} (extended, not in the DBC)"
                if message.is_extended_id
                else f"0x{can_id:03X} (not in the DBC)"
            )
            frames[name] = (can_id, {})
            counts[name] = counts.get(name, 0) + 1
            continue
        definition = protocol.message(can_id)
        counts[definition.name] = counts.get(definition.name, 0) + 1
        if len(data) != definition.length:
            frames[definition.name] = (can_id, len(data))
            continue
        frames[definition.name] = (
            can_id,
            dict(definition.decode(data, decode_choices=False)),  # type: ignore[arg-type]
        )
    return frames, counts


def replay(
    log: Path,
    config: RobotConfig | None = None,
    *,
    process: bool = False,
    tolerance: float = 0.0,
    tolerances: Mapping[str, float] | None = None,
    timeout: float = 10.0,
    controller: str = SOFTHIL,
    wait: float = WAIT,
) -> ReplayResult:
    """Replay `log` (any python-can format) against the controller `config` (default: the
    run's controller.json beside the log), in this process or as a separate program:
    softhil's, or `controller`, a user's command line (`hil.program`; always a process).
    The controller has `wait` s to send SYNC(0), then `timeout` s for each further frame."""
    check_controller(controller, external=False)
    if not 0 < wait <= MAX_WAIT:  # NaN too
        raise ReplayError(f"--wait: {wait:g} s; give 0 < SECONDS <= {MAX_WAIT:g} (a day)")
    if not has_direction(log):
        raise ReplayError(f"{log}: a .csv log cannot be replayed: {CSV_HAS_NO_DIRECTION}")
    protocol = Protocol()
    check_tolerances(protocol, tolerances or {})
    cycles = read_cycles(read_log(log), protocol, str(log))
    config = config or config_beside(log)
    if config.cycles != len(cycles) - 1:
        stopped = _stopped_early(Path(log)) if len(cycles) <= config.cycles else None
        raise ReplayError(
            f"{log}: {len(cycles)} SYNC cycles recorded, but the controller runs "
            f"{config.cycles + 1} "
            + (
                f"(the run stopped early: summary.json beside the log says {stopped})"
                if stopped
                else "(a log from a different scenario?)"
            )
        )
    if controller == SOFTHIL:
        check_served(cycles, config, protocol, str(log))
    if process or controller != SOFTHIL:
        sent = _replay_process(cycles, config, timeout, controller, wait)
    else:
        sent = _replay_thread(cycles, config, timeout, wait)
    return compare(cycles, sent, protocol, tolerance, tolerances)


def _stopped_early(log: Path) -> str | None:
    """What summary.json beside `log` says stopped its run, if the run recorded `log` and did
    not complete ("interrupted (SIGINT) at t = 12.220 s (after SYNC 1222 of 4000)", "failed:
    ..."); None otherwise."""
    try:
        summary = json.loads((log.parent / "summary.json").read_text())
        status, can_log = summary["status"], summary.get("can_log", log.name)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if status == "completed" or can_log != log.name:
        return None
    error = str(summary.get("error", ""))[:200]
    return error if error.startswith(status) else f"{status}: {error}" if error else status


def _replay_thread(
    cycles: Sequence[Cycle], config: RobotConfig, timeout: float, wait: float = WAIT
) -> list[list[can.Message]]:
    channel = f"softhil-replay-{uuid.uuid4().hex[:8]}"
    plant_bus = open_bus(BusSpec("virtual", channel))
    controller_bus = open_bus(BusSpec("virtual", channel))
    errors: list[BaseException] = []

    def work() -> None:
        try:
            ControllerNode(config, controller_bus).run()
        except Exception as exc:  # reported through alive()
            errors.append(exc)

    thread = threading.Thread(target=work, name="replayed-controller", daemon=True)
    plant = _ReplayPlant(cycles, plant_bus, timeout, wait=wait)
    try:
        thread.start()

        def alive() -> str | None:
            if thread.is_alive():
                return None
            return f"the controller stopped ({errors[0]})" if errors else "the controller stopped"

        plant.run(alive)
        thread.join(timeout)
    finally:
        plant_bus.shutdown()
        controller_bus.shutdown()
    if errors:
        raise ReplayError(f"the replayed controller failed: {errors[0]}")
    return plant.sent


def _replay_process(
    cycles: Sequence[Cycle],
    config: RobotConfig,
    timeout: float,
    controller: str = SOFTHIL,
    wait: float = WAIT,
) -> list[list[can.Message]]:
    from hil.bus.loopback import LoopbackHub

    hub = LoopbackHub("127.0.0.1").start()
    try:
        spec = BusSpec("loopback", "softhil", "127.0.0.1", hub.port)
        bus = open_bus(spec)
        with contextlib.ExitStack() as stack:
            stack.callback(bus.shutdown)
            folder = stack.enter_context(tempfile.TemporaryDirectory(prefix="softhil-replay-"))
            config_path = Path(folder) / "controller.json"
            config_path.write_text(config.to_json())
            report = Path(folder) / "controller_report.json"  # read by nobody: a replay compares
            log_path = Path(folder) / "controller.log"
            log = stack.enter_context(log_path.open("wb"))
            try:
                process = start(controller, config_path, spec, report, False, log)
            except HilError as exc:
                raise ReplayError(str(exc)) from None
            user = controller != SOFTHIL

            def said() -> str:
                words = last_words(log_path)
                return f" ({words})" if words else ""

            plant = _ReplayPlant(cycles, bus, timeout, USER_LINGER if user else None, wait)
            try:

                def alive() -> str | None:
                    code = process.poll()
                    if code is None:
                        return None
                    early = " before the log's final SYNC" if code == 0 else ""
                    return f"the controller exited with code {code}{early}{said()}"

                plant.run(alive)
                try:
                    # a user's program silent for USER_LINGER s after the final SYNC and still
                    # there serves until it is stopped: its frames are all in
                    code = process.wait(timeout=0.0 if user else timeout)
                except subprocess.TimeoutExpired:
                    if not user:
                        raise ReplayError(
                            f"the replayed controller did not exit within {timeout:g} s of the "
                            "final SYNC"
                        ) from None
                    code = 0
            finally:
                stop(process)  # with its process group: a shell's children go with it
            if code != 0:
                raise ReplayError(f"the replayed controller exited with code {code}{said()}")
            return plant.sent
    finally:
        hub.stop()


def assert_replays(
    log: str | os.PathLike[str],
    config: RobotConfig | None = None,
    *,
    tolerance: float = 0.0,
    tolerances: Mapping[str, float] | None = None,
    process: bool = False,
    controller: str = SOFTHIL,
    wait: float = WAIT,
) -> ReplayResult:
    """For pytest: replay a recorded run against a controller and fail on the first divergence.

    >>> from hil.replay import assert_replays
    >>> assert_replays("runs/default-1/can.log")          # doctest: +SKIP
    """
    result = replay(
        Path(log),
        config,
        process=process,
        tolerance=tolerance,
        tolerances=tolerances,
        controller=controller,
        wait=wait,
    )
    if not result.ok:
        raise AssertionError(
            f"{log}: {len(result.divergences)} divergence(s); first: {result.divergences[0]}"
            f"; by signal: {json.dumps(result.by_signal, sort_keys=True)}"
        )
    return result
