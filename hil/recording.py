"""Recorders of a run: the signals (column blocks, the CSV made from them, optionally MF4) and the
CAN log.

Signals are one row per SYNC, columns from the robot's signal specs, kept in column blocks and
written every FLUSH_INTERVAL of wall time as one Parquet file (`hil.blocks`: the format, why it
was chosen, the bytes of the CSV); `signals.csv` is written from the blocks when the recorder
closes, whatever stops the run, and `hil csv RUN` writes it after a run killed hard.
`signals.units.csv` gives every column's unit and meaning (`pandas.read_csv` reads either file
in one call).

The CAN log holds the frames as the plant logs them and writes them at every flush (at most
FLUSH_INTERVAL of wall time apart, and whenever a run stops), every frame stamped with the log's
start instant plus simulation time, so CAN tools see a real date (the default start is fixed, so
reruns stay byte-identical). A candump `.log` is written here, in whole lines
(`hil.results.RecordFile`): the lines of `candump -L -x`, `(seconds.micro) can0 ID#DATA T|R`,
T for frames the plant sent and R for frames it received, as python-can's CanutilsLogWriter
writes them (the tests compare them byte for byte, for every kind of frame). Every other suffix
(`.asc`, `.blf`, `.trc`, `.csv`, `.mf4`) is python-can's writer for it. Whatever stops a run, a
full disk included, leaves complete, readable files up to the last flush.
"""

from __future__ import annotations

import contextlib
import math
import operator
import time
from collections.abc import Callable, Iterable, Sequence
from itertools import repeat
from pathlib import Path

import can

from hil import blocks
from hil.errors import HilError
from hil.results import RecordFile, WriteError, write_file
from hil.rig import SignalSpec
from rigbus.protocol import frame_bits

UNITS_SUFFIX = blocks.UNITS_SUFFIX
FLUSH_INTERVAL = 0.25  # [s] of wall time between flushes of the recorders


class SignalRecorder:
    """One row per control period, in the robot's column order, written in column blocks."""

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
        units = [("time", "s", "simulation time of the SYNC")]
        units += [(s.column, s.unit, s.description) for s in self.specs]
        write_file(
            path.with_name(path.stem + UNITS_SUFFIX),
            blocks.header_line(["signal", "unit", "description"])
            + "".join(blocks.header_line(row) for row in units),
        )
        self._units = blocks.units_metadata({name: unit for name, unit, _ in units})
        self.blocks = blocks.blocks_folder(path)
        if self.blocks.exists():  # a results folder clears an earlier run's (--overwrite)
            raise WriteError(f"{self.blocks}: exists; the signal blocks need a new folder")
        self._flushed = time.monotonic()
        self._row: tuple[float, Sequence[float]] | None = None  # (time, sourced values)
        self._cells: dict[str, float] = {}
        # the cells of the next block, row after row (a flat list: see CanLogger._frames)
        self._pending: list[float] = []
        self._written = 0  # blocks written
        self._failed = False  # a block could not be written: the next ones are not tried
        self._closed = False
        self.rows = 0

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
        """End the open row (a number per column: a float, NaN where nobody wrote, an integer
        or a boolean); its block is written every FLUSH_INTERVAL of wall time."""
        if self._row is None:
            return
        time_, sourced = self._row
        cells = self._cells
        self._pending += self._in_order(  # NaN where nobody wrote
            [time_, *sourced, *map(cells.get, self._cell_columns, self._no_cells)]
        )
        if cells:
            cells.clear()
        self._row = None
        self.rows += 1
        now = time.monotonic()
        if now - self._flushed > FLUSH_INTERVAL:
            self._flushed = now
            self._write_block()

    def _write_block(self) -> None:
        """The pending rows as the next block file (none if there is no row, or a block
        failed before: the blocks on disk stay a run's first rows without a gap)."""
        cells, self._pending = self._pending, []
        if not cells or self._failed:
            return
        self._failed = True  # until the block is on disk
        first_row = self.rows - len(cells) // len(self.columns)
        data = blocks.encode_block(self.columns, cells, first_row, self._units)
        if not self._written:
            try:
                self.blocks.mkdir()
            except OSError as exc:
                raise WriteError(f"{self.blocks}: cannot create: {exc.strerror or exc}") from None
        write_file(self.blocks / blocks.part_name(self._written), data)
        self._written += 1
        self._failed = False

    def close(self) -> None:
        """End the open row, write the last block, then `path` (the CSV) from the blocks on disk.
        After a failure (raised once: a full disk, a cell that is not a number) the CSV of the
        blocks written before it is tried quietly."""
        if self._closed:
            return
        self._closed = True
        try:
            if not self._failed:
                self.end_row()
                self._write_block()
        finally:
            if not self._failed:
                blocks.write_csv(self.path, self.columns)
            else:
                with contextlib.suppress(HilError, OSError):
                    blocks.write_csv(self.path, self.columns)

    def write_mf4(self, path: Path) -> None:
        """The signals as an MF4 file (asammdf) from the blocks, with units and comments."""
        require_asammdf(path.name)
        from asammdf import MDF, Signal

        columns, data = blocks.read_columns(self.blocks)
        if not columns:
            data = data.reshape(len(self.columns), 0)
        t = data[0]
        mdf = MDF(version="4.10")
        mdf.append(
            [
                Signal(data[i + 1], t, name=s.column, unit=s.unit, comment=s.description)
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


_DATA = operator.attrgetter("data")
_FRAME_BITS = tuple(frame_bits(dlc) for dlc in range(65))  # by data length (FD: up to 64)


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


_CHANNEL_DEFAULT = "can0"
_END = {False: " T\n", True: " R\n"}  # a candump line's end, by received
_ERROR_ID = f"{0x20000000 | 0x80:08X}#"  # CAN_ERR_FLAG | CAN_ERR_BUSERROR, as python-can writes
_FD_FLAGS = ("0", "1", "2", "3")  # "##" then BRS (1) | ESI (2), in hex


class _Idents(dict[tuple[int, bool], str]):
    """ "ID#" of a frame as candump writes it, by (id, extended), made once per id."""

    def __missing__(self, key: tuple[int, bool]) -> str:
        can_id, extended = key
        ident = self[key] = f"{can_id:08X}#" if extended else f"{can_id:03X}#"
        return ident


class CanLogger:
    """The CAN log as the plant sees the bus: T for frames the plant sent, R for frames it
    received, stamped `start + simulation time`. The frames are held as logged and written at
    every flush; they must not change after they are logged (the plant's never do)."""

    def __init__(self, path: Path, start: float = 0.0, channel: str = _CHANNEL_DEFAULT) -> None:
        self.path = path
        self.start = start
        self.channel = channel
        self._record: RecordFile | None = None
        self._writer: can.io.generic.MessageWriter | None = None
        try:
            if path.suffix == ".log":
                self._record = RecordFile(path)
            elif path.suffix == ".asc":
                self._writer = _AscWriter(path, start)
            else:
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
        # the frames logged since the last flush, each with its time and direction, in flat lists:
        # no container made a frame, so holding them costs the garbage collector nothing (a
        # tuple a frame, held for a flush, made its collections scan them: 3-10x the appends)
        self._frames: list[can.Message] = []
        self._times: list[float] = []
        self._received: list[bool] = []
        # a candump line's channel, as python-can writes it: a bare number n is "can<n>"
        self._candump_channel = f"can{channel}" if channel.isdigit() else channel
        self._first_stamp: float | None = None  # the first frame's stamp (candump)
        self._idents = _Idents()

    def log_all(self, messages: Sequence[can.Message], time: float, received: bool) -> None:
        """Frames sent or received together, at one time [s] of simulation."""
        self._frames += messages
        self._times += repeat(time, len(messages))
        self._received += repeat(received, len(messages))

    def log(self, message: can.Message, time: float, received: bool) -> None:
        """One frame the plant sent (T) or received (R) at `time` [s] of simulation."""
        self._frames.append(message)
        self._times.append(time)
        self._received.append(received)

    def flush(self, force: bool = False) -> None:
        """Write the frames logged since the last flush, whole records on disk: every
        FLUSH_INTERVAL of wall time, or now with `force`. A .blf or .mf4 is whole once closed."""
        now = time.monotonic()
        if force or now - self._flushed > FLUSH_INTERVAL:
            self._flushed = now
            self._write_pending()
            if self._record is not None:
                self._record.flush()

    def close(self) -> None:
        """Write what is held and close the log; a log that already failed closes quietly (the
        failure was raised)."""
        try:
            self._write_pending()
        finally:
            if self._record is not None:
                self._record.close()
        if self._writer is not None:
            try:
                self._writer.stop()
            except OSError as exc:
                raise WriteError(f"{self.path}: cannot write: {exc.strerror or exc}") from None

    def _write_pending(self) -> None:
        """Write the frames held, and count them (sent, received, bits on the bus)."""
        frames, times, received = self._frames, self._times, self._received
        if not frames:
            return
        self._frames, self._times, self._received = [], [], []
        if self._record is not None:
            self._record.write("".join(self._candump_lines(frames, times, received)))
        else:
            self._write_python_can(frames, times, received)
        count = sum(received)
        self.received += count
        self.sent += len(frames) - count
        self.bits += sum(map(_FRAME_BITS.__getitem__, map(len, map(_DATA, frames))))

    def _candump_lines(
        self, frames: list[can.Message], times: list[float], received: list[bool]
    ) -> list[str]:
        """The candump lines of the frames, as python-can's CanutilsLogWriter writes them: a
        stamp before the log's first written as the first; an error frame with python-can's
        error id and no direction; a remote frame's data "R"; an FD frame's "#" and flags."""
        lines: list[str] = []
        add = lines.append
        idents = self._idents
        last = math.nan  # the stamp `prefix` was made for
        prefix = ""
        for m, at, rx in zip(frames, times, received, strict=True):
            stamp = self.start + at
            if stamp != last or stamp == 0.0:  # a SYNC's frames share a stamp, formatted once
                last = stamp  # (a zero's sign shows: -0.0 is formatted apart)
                if self._first_stamp is None:
                    self._first_stamp = stamp or 0.0
                elif stamp < self._first_stamp:
                    stamp = self._first_stamp
                prefix = f"({stamp:f}) {self._candump_channel} "
            if m.is_error_frame or m.is_remote_frame or m.is_fd:
                add(prefix + _unusual_line(m, idents, _END[rx]))
            else:
                ident = idents[m.arbitration_id, m.is_extended_id]
                add(f"{prefix}{ident}{m.data.hex().upper()}{_END[rx]}")
        return lines

    def _write_python_can(
        self, frames: list[can.Message], times: list[float], received: list[bool]
    ) -> None:
        """The frames through python-can's writer for the log's suffix."""
        assert self._writer is not None
        try:
            for message, at, rx in zip(frames, times, received, strict=True):
                self._writer.on_message_received(
                    can.Message(
                        timestamp=self.start + at,
                        arbitration_id=message.arbitration_id,
                        is_extended_id=message.is_extended_id,
                        is_remote_frame=message.is_remote_frame,
                        is_error_frame=message.is_error_frame,
                        is_fd=message.is_fd,
                        bitrate_switch=message.bitrate_switch,
                        error_state_indicator=message.error_state_indicator,
                        dlc=message.dlc,
                        data=None if message.is_remote_frame else bytes(message.data),
                        is_rx=rx,
                        channel=self.channel,
                    )
                )
        except OSError as exc:
            raise WriteError(f"{self.path}: cannot write: {exc.strerror or exc}") from None


def _unusual_line(message: can.Message, idents: _Idents, end: str) -> str:
    """A candump line's "ID#DATA end" for an error, remote or FD frame, as python-can writes it."""
    if message.is_error_frame:
        ident, end = _ERROR_ID, "\n"
    else:
        ident = idents[(message.arbitration_id, message.is_extended_id)]
    if message.is_remote_frame:
        return f"{ident}R{end}"
    flags = ""
    if message.is_fd:
        flags = "#" + _FD_FLAGS[message.bitrate_switch | message.error_state_indicator << 1]
    return f"{ident}{flags}{message.data.hex().upper()}{end}"
