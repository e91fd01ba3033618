"""Recorders of a run: the signals (CSV with a units sidecar, optionally MF4) and the CAN log.

The CAN log is written by python-can's writer for its file suffix (`.log` candump, `.asc`,
`.blf`, `.trc`, `.csv`, `.mf4`), every frame stamped with the log's start instant plus simulation
time, so CAN tools see a real date (the default start is fixed, so reruns stay byte-identical).
The `.log` lines are those of `candump -L -x`: `(seconds.micro) can0 ID#DATA T|R`, T for frames
the plant sent and R for frames it received.

Signals are one CSV row per SYNC, columns from the robot's signal specs; `signals.units.csv`
beside it gives every column's unit and meaning (`pandas.read_csv` reads either in one call).
Both the CSV and a candump log are written in whole records (`hil.results.RecordFile`), in
blocks at most FLUSH_INTERVAL of wall time apart and whenever a run stops, so whatever stops a
run, a full disk included, leaves complete, readable files up to the last flushed control
period, without a system call per SYNC. Values are written as `repr` writes them (in C:
`hil.cformat`), so equal runs give byte-identical files.
"""

from __future__ import annotations

import csv
import io
import math
import operator
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TextIO, cast

import can

from hil import cformat
from hil.errors import HilError
from hil.results import RecordFile, WriteError, write_file
from hil.rig import SignalSpec
from rigbus.protocol import frame_bits

UNITS_SUFFIX = ".units.csv"
_NUMBERS = (float, int)  # the types of a row's cells written by `",".join(map(repr, ...))`
FLUSH_INTERVAL = 0.25  # [s] of wall time between flushes of the recorders


class SignalRecorder:
    """One CSV row per control period, in the robot's column order."""

    def __init__(self, path: Path, specs: Sequence[SignalSpec]) -> None:
        self.path = path
        self.specs = list(specs)
        self.columns = ["time"] + [s.column for s in self.specs]
        # a row is put together from the SYNC's time, the plant's values of the columns with a
        # source (in `source_columns` order, `begin_row`) and the cells frames fill (the other
        # columns, NaN where nobody wrote), in column order in one call
        self.source_columns = [s.column for s in self.specs if s.source is not None]
        sourced = set(self.source_columns)
        self._cell_columns = [c for c in self.columns[1:] if c not in sourced]
        position = {c: i for i, c in enumerate(["time", *self.source_columns, *self._cell_columns])}
        order = [position[c] for c in self.columns]
        self._in_order: Callable[[list[float]], Sequence[float]] = (
            operator.itemgetter(*order) if len(order) > 1 else lambda parts: parts[:1]
        )
        self._no_cells = [math.nan] * len(self._cell_columns)
        # the recorded signals of each frame (kind, index): (signal, column) pairs
        self._by_frame: dict[tuple[str, int | None], list[tuple[str, str]]] = {}
        for s in self.specs:
            if s.frame is not None:
                kind, index, name = s.frame
                self._by_frame.setdefault((kind, index), []).append((name, s.column))
        units = io.StringIO()
        writer = csv.writer(units, lineterminator="\n")
        writer.writerow(["signal", "unit", "description"])
        writer.writerow(["time", "s", "simulation time of the SYNC"])
        for s in self.specs:
            writer.writerow([s.column, s.unit, s.description])
        write_file(path.with_name(path.stem + UNITS_SUFFIX), units.getvalue())
        self._file = RecordFile(path)
        self._flushed = time.monotonic()
        self._writer = csv.writer(self._file, lineterminator="\n")
        self._writer.writerow(self.columns)
        self._file.flush()
        self._row: tuple[float, Sequence[float]] | None = None  # (time, sourced values)
        self._cells: dict[str, float] = {}
        module = cformat.load()
        self._format_row = module.format_row if module is not None else None
        self.rows = 0
        self.table: list[list[float]] = []  # every row, for the MF4 copy and the summary

    def begin_row(self, time: float, values: Sequence[float]) -> None:
        """Start the row of a SYNC with the plant's values of `source_columns`, in that order
        (held until the row ends: the caller must not change them)."""
        if len(values) != len(self.source_columns):
            raise HilError(
                f"{self.path.name}: a row of {len(values)} values for "
                f"{len(self.source_columns)} sourced columns"
            )
        self.end_row()
        self._row = (time, values)

    def frame_columns(self, kind: str, index: int | None) -> list[tuple[str, str]]:
        """(signal, column) of every recorded signal of frame (kind, index)."""
        return list(self._by_frame.get((kind, index), ()))

    def set_cells(self, cells: Iterable[tuple[str, float]]) -> None:
        """(column, value) pairs into the open row: what a frame reported (the controller's
        state), its columns looked up once (`frame_columns`); the columns with a source take
        the plant's values, not these."""
        if self._row is not None:
            self._cells.update(cells)

    def end_row(self) -> None:
        if self._row is None:
            return
        time_, sourced = self._row
        cells = self._cells
        values = list(  # NaN where nobody wrote
            self._in_order([time_, *sourced, *map(cells.get, self._cell_columns, self._no_cells)])
        )
        if cells:
            cells.clear()
        line = self._format_row(values) if self._format_row is not None else None
        if line is not None:  # floats and ints, the usual row: written in C
            self._file.write(line)
        else:
            self._write_row(values)
        now = time.monotonic()
        if now - self._flushed > FLUSH_INTERVAL:  # blocks of whole records, not a write a SYNC
            self._file.flush()
            self._flushed = now
        self.table.append(values)
        self._row = None
        self.rows += 1

    def _write_row(self, values: list[float]) -> None:
        """`values` as csv.writer writes the list of their texts: a NaN float an empty cell,
        everything else its repr (v != v: NaN, as math.isnan). Numbers alone: their reprs
        joined, which is what csv.writer writes for them (no repr of an int or a finite float
        has a character to quote)."""
        line = ",".join(map(repr, values))
        if "n" in line or not all(type(v) in _NUMBERS for v in values):  # nan, inf, or more
            self._writer.writerow(
                ["" if isinstance(v, float) and v != v else repr(v) for v in values]
            )
        else:
            self._file.write(line + "\n")

    def close(self) -> None:
        if not self._file.closed:
            self.end_row()
            self._file.close()

    def write_mf4(self, path: Path) -> None:
        """The signals as an MF4 file (asammdf), with units and comments."""
        import numpy as np

        require_asammdf(path.name)
        from asammdf import MDF, Signal

        data = np.array(self.table, dtype=float).reshape(-1, len(self.columns))
        t = data[:, 0]
        mdf = MDF(version="4.10")
        mdf.append(
            [
                Signal(data[:, i + 1], t, name=s.column, unit=s.unit, comment=s.description)
                for i, s in enumerate(self.specs)
            ],
            comment="softhil signals",
        )
        mdf.save(str(path), overwrite=True)


def require_asammdf(what: str) -> None:
    """HilError naming `what` (the flag, key or file asking for MF4) unless asammdf, which writes
    MF4, can be imported: a run checks it before it starts, not after."""
    try:
        import asammdf  # noqa: F401
    except ImportError:
        raise HilError(
            f"{what}: MF4 needs asammdf, which is not installed: pip install asammdf"
        ) from None


_FRAME_BITS = tuple(frame_bits(dlc) for dlc in range(65))  # by data length (FD: up to 64)
_DIRECTION = {False: " T\n", True: " R\n"}  # a candump line's end, by received


class _AscWriter(can.ASCWriter):
    """python-can's ASC writer, its `date` header set to the log's start instead of the wall
    clock (so that reruns give byte-identical files, and the date is the measurement's)."""

    def __init__(self, path: Path, start: float) -> None:
        import datetime as dt

        super().__init__(str(path))
        self.file.seek(0)
        self.file.truncate()
        stamp = dt.datetime.fromtimestamp(start, tz=dt.UTC)
        self.file.write(f"date {self._format_header_datetime(stamp)}\n")
        self.file.write("base hex  timestamps absolute\n")
        self.file.write("internal events logged\n")


class CanLogger:
    """The CAN log as the plant sees the bus: T for frames the plant sent, R for frames it
    received, stamped `start + simulation time`; the writer is python-can's for the suffix."""

    def __init__(self, path: Path, start: float = 0.0, channel: str = "can0") -> None:
        self.path = path
        self.start = start
        self.channel = channel
        try:
            if path.suffix == ".log":
                self._record: RecordFile | None = RecordFile(path)
                self._writer: can.io.generic.MessageWriter = can.CanutilsLogWriter(
                    cast(TextIO, self._record)  # a text file that writes whole records
                )
            elif path.suffix == ".asc":
                self._record = None
                self._writer = _AscWriter(path, start)
            else:
                self._record = None
                self._writer = can.Logger(str(path))  # type: ignore[abstract]
                if isinstance(self._writer, can.TRCWriter):  # its header names the file, not
                    self._writer.filepath = path.name  # the folder: the same in every folder
        except OSError as exc:
            raise WriteError(f"{path}: cannot create: {exc.strerror or exc}") from None
        except (ImportError, NotImplementedError) as exc:  # python-can's MF4 writer: the latter
            raise HilError(f"{path.name}: this log format needs an extra package ({exc})") from None
        except ValueError as exc:
            raise HilError(f"{path.name}: {exc}") from None
        self._flushed = time.monotonic()
        self.sent = 0
        self.received = 0
        self.bits = 0
        # candump lines are written here directly (`log_all`), as python-can's
        # CanutilsLogWriter writes them (checked byte for byte in the tests) without building a
        # message per frame; its channel rule: a bare number n is "can<n>"
        self._candump_channel = f"can{channel}" if channel.isdigit() else channel
        self._first_stamp: float | None = None
        self._idents: dict[tuple[int, bool], str] = {}  # "ID#" as written, by (id, extended)
        self._stamp = math.nan  # the last stamp written, and its "(seconds) channel " text
        self._stamp_text = ""
        module = cformat.load()  # the lines of classic data frames in C
        self._lines = module.candump_lines if module is not None else None
        # frames `log` took at one time and direction, written together (`_write_held`) before
        # anything else is written: the plant receives a period's commands one by one
        self._held: list[can.Message] = []
        self._held_at = (0.0, False)  # their (time, received)

    def _stamp_prefix(self, stamp: float) -> str:
        """The "(seconds) channel " that CanutilsLogWriter writes before a frame stamped `stamp`
        [s]: as it does, a stamp before the log's first is written as the first. The frames of a
        SYNC share a stamp, so its text is formatted once (a zero stamp always: -0.0 prints
        apart)."""
        if self._first_stamp is None:
            self._first_stamp = stamp or 0.0
        elif stamp < self._first_stamp:
            stamp = self._first_stamp
        if stamp != self._stamp or stamp == 0.0:
            self._stamp = stamp
            self._stamp_text = f"({stamp:f}) {self._candump_channel} "
        return self._stamp_text

    def _ident(self, message: can.Message) -> str:
        """ "ID#" as CanutilsLogWriter writes it, remembered by (id, extended)."""
        key = (message.arbitration_id, message.is_extended_id)
        ident = self._idents.get(key)
        if ident is None:
            can_id = message.arbitration_id
            ident = f"{can_id:08X}#" if message.is_extended_id else f"{can_id:03X}#"
            self._idents[key] = ident
        return ident

    def log_all(self, messages: Sequence[can.Message], time: float, received: bool) -> None:
        """`log` of each message in turn (frames sent or received together, at one time)."""
        if self._held:
            self._write_held()
        self._log_all(messages, time, received)

    def _log_all(self, messages: Sequence[can.Message], time: float, received: bool) -> None:
        if self._record is None:
            for message in messages:
                self._write(message, time, received)
            return
        prefix = self._stamp_prefix(self.start + time)
        end = _DIRECTION[received]
        if self._lines is not None:  # in C: classic data frames, the usual case
            done = self._lines(prefix, messages, end, _FRAME_BITS)
            if done is not None:
                self._record.write(done[0])
                self._count(done[1], len(messages), received)
                return
        for message in messages:
            self._line(prefix, message, end, received)

    def log(self, message: can.Message, time: float, received: bool) -> None:
        """One frame the plant sent (T) or received (R), stamped start + `time`: held with the
        frames logged before it at the same time and direction, and written with them, in order,
        before anything else is written (`log_all`, `flush`, `close`, another time)."""
        if self._held and (
            (time, received) != self._held_at or self.start + time == 0.0  # -0.0 prints apart
        ):
            self._write_held()
        if not self._held:
            self._held_at = (time, received)
        self._held.append(message)

    def _write_held(self) -> None:
        messages, self._held = self._held, []
        self._log_all(messages, *self._held_at)

    def _line(self, prefix: str, message: can.Message, end: str, received: bool) -> None:
        """The candump line of one frame, in Python: a classic data frame's as CanutilsLogWriter
        writes it, any other (error, remote, FD) by CanutilsLogWriter itself."""
        if message.is_error_frame or message.is_remote_frame or message.is_fd:
            self._writer.last_timestamp = self._first_stamp  # type: ignore[attr-defined]
            self._writer.on_message_received(
                can.Message(
                    timestamp=self._stamp,
                    arbitration_id=message.arbitration_id,
                    is_extended_id=message.is_extended_id,
                    is_remote_frame=message.is_remote_frame,
                    is_error_frame=message.is_error_frame,
                    is_fd=message.is_fd,
                    bitrate_switch=message.bitrate_switch,
                    error_state_indicator=message.error_state_indicator,
                    dlc=message.dlc,
                    data=None if message.is_remote_frame else bytes(message.data),
                    is_rx=received,
                    channel=self.channel,
                )
            )
        else:
            data = message.data
            self._record.write(f"{prefix}{self._ident(message)}{data.hex().upper()}{end}")  # type: ignore[union-attr]
        self._count(_FRAME_BITS[len(message.data)], 1, received)

    def _count(self, bits: int, frames: int, received: bool) -> None:
        self.bits += bits
        if received:
            self.received += frames
        else:
            self.sent += frames

    def _write(self, message: can.Message, time: float, received: bool) -> None:
        """One frame through python-can's writer for the log's suffix."""
        stamped = can.Message(
            timestamp=self.start + time,
            arbitration_id=message.arbitration_id,
            is_extended_id=message.is_extended_id,
            data=bytes(message.data),
            is_rx=received,
            channel=self.channel,
        )
        try:
            self._writer.on_message_received(stamped)
        except OSError as exc:
            raise WriteError(f"{self.path}: cannot write: {exc.strerror or exc}") from None
        self._count(_FRAME_BITS[len(message.data)], 1, received)

    def flush(self, force: bool = False) -> None:
        """Whole records on disk, in blocks (every FLUSH_INTERVAL of wall time, or now with
        `force`) for the line formats; binary formats (BLF, MF4) are complete when closed."""
        if self._held:
            self._write_held()
        now = time.monotonic()
        if self._record is not None and (force or now - self._flushed > FLUSH_INTERVAL):
            self._record.flush()
            self._flushed = now

    def close(self) -> None:
        """Close the log; a log that already failed closes quietly (the failure was raised)."""
        try:
            if self._held:
                self._write_held()
            self._writer.stop()
        except OSError as exc:
            raise WriteError(f"{self.path}: cannot write: {exc.strerror or exc}") from None
