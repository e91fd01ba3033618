"""`hil bus replay`: transmit the frames of a log onto a bus, timed or in lockstep.

Which frames: the direction flag of each frame selects them (`direction`: "R" the frames the
logging node received, "T" those it transmitted, "all" both; a log without a direction, .csv,
is replayed whole: `hil bus replay` refuses R or T for it), then the optional id/name filter.
In a softhil run log (the plant's view) R are the controller's frames (SYNC, DriveCommand,
ControllerState) and T the plant's.

Timed (`speed` X): each frame leaves at (its log time - the first frame's log time) / X on the
monotonic wall clock; X = 2 replays twice as fast.

Lockstep: no timing. The log is cut into SYNC cycles (a SYNC frame, id 0x080, and everything
after it up to the next SYNC; frames before the first SYNC form cycle "pre"). Within a cycle the
frames are taken in log order: a selected frame is sent; an unselected frame that carries the
SYNC counter and is produced once per cycle (SYNC, DriveStatus*, DriveCommand*,
ControllerState*) is an acknowledgement point: replay waits there until the bus has carried a
frame with that id and that counter value (each seen frame satisfies one wait). So replaying
the controller's frames (R) of a plant log against a live plant sends SYNC(c), waits for every
DriveStatus(c) the log holds, then sends the commands of c; replaying the plant's frames (T)
against a live controller waits for SYNC(c), sends the status and camera frames, then waits for
the controller's commands of c. Event frames (EMCY, heartbeat, camera markers) are never
waited for. A wait longer than `timeout` stops replay with one line naming the frame,
the counter and the cycle.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import can
from cantools.database.can import Database

from hil.bustools.frames import FrameFilter, counter_of, dbc_message
from hil.bustools.send import send_one
from hil.errors import BusError, HilError
from rigbus.protocol import SYNC_ID

DIRECTIONS = ("R", "T", "all")
ACK_PREFIXES = ("SYNC", "DriveStatus", "DriveCommand", "ControllerState")


def selected(msg: can.Message, direction: str, selection: FrameFilter) -> bool:
    if direction == "R" and not msg.is_rx:
        return False
    if direction == "T" and msg.is_rx:
        return False
    return selection.matches(msg)


def outgoing(msg: can.Message) -> can.Message:
    """A fresh copy for transmission (no log timestamp, channel or direction)."""
    return can.Message(
        arbitration_id=msg.arbitration_id,
        is_extended_id=msg.is_extended_id,
        is_remote_frame=msg.is_remote_frame,
        dlc=msg.dlc,
        data=None if msg.is_remote_frame else bytes(msg.data),
    )


@dataclass
class ReplayCount:
    sent: int = 0
    cycles: int = 0
    acknowledged: int = 0

    def line(self) -> str:
        text = f"replayed {self.sent} frames"
        if self.cycles:
            text += f" in {self.cycles} SYNC cycles, {self.acknowledged} acknowledgements"
        return text


def replay_timed(
    bus: can.BusABC,
    messages: list[can.Message],
    direction: str,
    selection: FrameFilter,
    speed: float,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> ReplayCount:
    """Send the selected frames keeping their relative log timing, scaled by 1/speed."""
    if not speed > 0:
        raise HilError(f"--speed must be positive, got {speed}")
    tally = ReplayCount()
    chosen = [m for m in messages if selected(m, direction, selection)]
    if not chosen:
        return tally
    first = chosen[0].timestamp
    start = clock()
    for msg in chosen:
        due = start + (msg.timestamp - first) / speed
        wait = due - clock()
        if wait > 0:
            sleep(wait)  # pacing against the wall clock is this mode's job
        send_one(bus, outgoing(msg))
        tally.sent += 1
    return tally


def is_ack_frame(database: Database, msg: can.Message) -> bool:
    message = dbc_message(database, msg)
    return message is not None and message.name.startswith(ACK_PREFIXES)


def check_lockstep_direction(direction: str) -> None:
    if direction not in ("R", "T"):
        raise HilError(
            "--lockstep waits for the other side's frames: choose the side to replay with "
            "--direction R (the controller's frames of a plant log) or T (the plant's)"
        )


def replay_lockstep(
    bus: can.BusABC,
    messages: list[can.Message],
    direction: str,
    selection: FrameFilter,
    database: Database,
    timeout: float,
) -> ReplayCount:
    """Send the selected frames cycle by cycle, waiting for the receiver's echoes (see module)."""
    check_lockstep_direction(direction)
    tally = ReplayCount()
    seen: Counter[tuple[int, int]] = Counter()
    cycle = "pre"
    for index, msg in enumerate(messages, start=1):
        if msg.arbitration_id == SYNC_ID and not msg.is_extended_id:
            counter = counter_of(database, msg)
            cycle = str(counter) if counter is not None else cycle
            tally.cycles += 1
        if selected(msg, direction, selection):
            send_one(bus, outgoing(msg))
            tally.sent += 1
            continue
        if not is_ack_frame(database, msg):
            continue
        counter = counter_of(database, msg)
        if counter is None:
            continue
        _await(bus, database, (msg.arbitration_id, counter), seen, timeout, cycle, index)
        tally.acknowledged += 1
    return tally


def _await(
    bus: can.BusABC,
    database: Database,
    wanted: tuple[int, int],
    seen: Counter[tuple[int, int]],
    timeout: float,
    cycle: str,
    index: int,
) -> None:
    deadline = time.monotonic() + timeout
    while seen[wanted] == 0:
        left = deadline - time.monotonic()
        msg = bus.recv(max(0.0, left)) if left > 0 else None
        if msg is None:
            message = database.get_message_by_frame_id(wanted[0])
            raise BusError(
                f"lockstep replay: no {message.name} (0x{wanted[0]:03X}) with counter "
                f"{wanted[1]} within {timeout:g} s (SYNC cycle {cycle}, log frame {index}); "
                "is the receiver running on this bus?"
            )
        counter = counter_of(database, msg)
        if counter is not None:
            seen[(msg.arbitration_id, counter)] += 1
    seen[wanted] -= 1
