"""Recorders of a run: the signals CSV and the CAN log (candump `.log`), written as the run goes.

Both are flushed at every SYNC, so whatever stops a run (a dead controller, an FMU error, Ctrl-C)
leaves complete, readable files up to the last finished control period. Values are written with
`repr`, so equal runs give byte-identical files.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import TextIO

import can

PER_SEGMENT = (
    "kappa_ref",
    "kappa_est",
    "kappa",
    "theta",
    "p_a",
    "p_b",
    "x",
    "x_ref",
    "v",
    "i_motor",
    "fault",
)


def signal_columns(segments: int) -> list[str]:
    return ["time"] + [f"{name}_{i}" for i in range(1, segments + 1) for name in PER_SEGMENT]


class SignalRecorder:
    """One CSV row per control period: reference, controller estimate and the true state."""

    def __init__(self, path: Path, segments: int) -> None:
        self.path = path
        self.segments = segments
        self._file: TextIO = path.open("w", newline="")
        self._writer = csv.writer(self._file, lineterminator="\n")
        self._writer.writerow(signal_columns(segments))
        self._row: dict[str, float] | None = None
        self.rows = 0

    def begin_row(self, time: float, values: dict[str, float]) -> None:
        """Start the row of a SYNC; values are keyed `name_i` (see PER_SEGMENT)."""
        self.end_row()
        self._row = {"time": time, **values}

    def controller_state(self, node: int, kappa_ref: float, kappa_est: float) -> None:
        """The controller's estimate for the open row (its reference is the plant's own)."""
        if self._row is not None:
            self._row[f"kappa_est_{node}"] = kappa_est

    def end_row(self) -> None:
        if self._row is None:
            return
        columns = signal_columns(self.segments)
        self._writer.writerow([_format(self._row.get(c, math.nan)) for c in columns])
        self._file.flush()
        self._row = None
        self.rows += 1

    def close(self) -> None:
        if not self._file.closed:
            self.end_row()
            self._file.close()


def _format(value: float) -> str:
    return "" if isinstance(value, float) and math.isnan(value) else repr(value)


class CanLogger:
    """The CAN log as the plant sees the bus, stamped with simulation time (candump -L format,
    written by python-can): T for frames the plant sent, R for frames it received."""

    def __init__(self, path: Path, channel: str = "can0") -> None:
        self.path = path
        self.channel = channel
        self._writer = can.CanutilsLogWriter(str(path), channel=channel)
        self.sent = 0
        self.received = 0
        self.bits = 0

    def log(self, message: can.Message, time: float, received: bool) -> None:
        from controllers.protocol import frame_bits

        stamped = can.Message(
            timestamp=time,
            arbitration_id=message.arbitration_id,
            is_extended_id=message.is_extended_id,
            data=bytes(message.data),
            is_rx=received,
            channel=self.channel,
        )
        self._writer.on_message_received(stamped)
        self.bits += frame_bits(len(message.data))
        if received:
            self.received += 1
        else:
            self.sent += 1

    def flush(self) -> None:
        self._writer.file.flush()

    def close(self) -> None:
        self._writer.stop()
