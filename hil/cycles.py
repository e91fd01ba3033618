"""A plant-side CAN log read as its SYNC cycles: what `hil replay` plays back and the
estimators' report (`hil.estimation`) scores.

A softhil CAN log holds both sides of every cycle, seen from the plant: after the SYNC(c) that
the controller sent (R), the frames the plant answered with (T), then the frames the controller
sent in answer to cycle c (R). `read_cycles` splits it so; `read_log` reads a log of any format
python-can reads and `config_beside` the controller configuration recorded beside it.
Invariant: every frame of a cycle decodes with the protocol, and the SYNC counters follow one
another, or the log is refused (ReplayError naming the file and the frame).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from hil.bustools.logs import DIRECTED, NO_DIRECTION
from hil.errors import ReplayError
from hil.seam import read_config
from rigbus.protocol import COUNTER_MODULO, SYNC_ID, FrameError, Protocol, Sync


@dataclass(frozen=True)
class Cycle:
    """One recorded cycle: the plant's answer to SYNC(c) and the controller's frames after it."""

    index: int
    time: float  # simulation time of the SYNC [s] (log timestamp less the log's first SYNC)
    plant: tuple[can.Message, ...]
    controller: tuple[can.Message, ...]


# why a python-can CSV log serves neither replay nor the estimation report
CSV_HAS_NO_DIRECTION = (
    f"{NO_DIRECTION}, so the controller's frames cannot be told from the plant's (record with "
    f"--can-log can{DIRECTED})"
)


def read_cycles(messages: Iterable[can.Message], protocol: Protocol, source: str) -> list[Cycle]:
    """Split a plant-side log into cycles; ReplayError names the file and the problem."""
    cycles: list[Cycle] = []
    plant: list[can.Message] = []
    controller: list[can.Message] = []
    start: float | None = None
    counter = -1
    for number, message in enumerate(messages, start=1):
        if message.arbitration_id == SYNC_ID and message.is_rx:
            try:
                frame = protocol.decode(message)
            except FrameError as exc:
                raise ReplayError(f"{source}: frame {number}: {exc}") from None
            assert isinstance(frame, Sync)
            expected = (counter + 1) % COUNTER_MODULO
            if frame.counter != expected:
                raise ReplayError(
                    f"{source}: frame {number}: SYNC counter {frame.counter} where {expected} "
                    "was due (a log of a different run, or frames missing)"
                )
            if counter >= 0:
                cycles[-1] = Cycle(
                    cycles[-1].index, cycles[-1].time, tuple(plant), tuple(controller)
                )
            counter += 1
            if start is None:
                start = message.timestamp
            cycles.append(Cycle(counter, round(message.timestamp - start, 6), (), ()))
            plant, controller = [], []
            continue
        if counter < 0:
            continue  # before the first SYNC: not part of a cycle
        try:
            protocol.decode(message)
        except FrameError as exc:
            raise ReplayError(f"{source}: frame {number}: {exc}") from None
        (controller if message.is_rx else plant).append(message)
    if not cycles:
        raise ReplayError(
            f"{source}: no SYNC frame received by the plant (R 080): nothing to replay"
        )
    cycles[-1] = Cycle(cycles[-1].index, cycles[-1].time, tuple(plant), tuple(controller))
    return cycles


def read_log(path: Path) -> list[can.Message]:
    """The messages of a CAN log in any format python-can reads (by suffix); a malformed log is
    one line naming the file and where."""
    from hil.bustools.logs import LogError
    from hil.bustools.logs import read_log as read

    try:
        return read(path)
    except LogError as exc:
        raise ReplayError(str(exc)) from None


def config_beside(
    log: Path, missing: str = "give --scenario to say which controller to replay"
) -> Any:
    """The controller configuration a run recorded beside its log (controller.json), of
    whichever robot kind its `robot` key names (a fish run's is not the arm's); without one,
    ReplayError ending in `missing` (what the caller needs it for, or how to do without)."""
    path = log.parent / "controller.json"
    try:
        return read_config(path.read_text())
    except FileNotFoundError:
        raise ReplayError(f"{path}: no controller.json beside the log; {missing}") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ReplayError(f"{path}: {exc}") from None
