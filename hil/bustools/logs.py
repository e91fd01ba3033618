"""Reading and writing CAN logs in every format python-can knows, chosen by file suffix.

`read_log` turns every malformed input (an unknown suffix, an empty log, a garbage line, a
random-byte binary file, a truncated one with no complete frame) into one `LogError` naming the
file and where: the line number of text formats, the record number of binary ones. It is
stricter than python-can's readers, which silently change some frames (an odd number of data
digits, an id beyond 29 bits masked, a dlc the data does not fill): those are malformed lines
too. A .blf cut short, or a text log cut inside its last line, yields its frames before the cut
and a warning (`iter_log`).

`write_log` writes by suffix through `can.Logger` and removes the file again if writing fails,
so a failure never leaves a half-written log behind under the requested name.
"""

from __future__ import annotations

import contextlib
import gc
import re
import sys
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TextIO

import can

from hil.errors import HilError

TEXT_SUFFIXES = (".log", ".asc", ".trc", ".csv")
BINARY_SUFFIXES = (".blf", ".mf4")
SUFFIXES = TEXT_SUFFIXES + BINARY_SUFFIXES
MAX_STD_ID = 0x7FF
MAX_EXT_ID = 0x1FFFFFFF

# Vector ASC: header keywords, trigger block markers, comments; every event line starts with a
# timestamp (messages, statistics, error frames...), which python-can reads or skips itself.
_ASC_ACCEPTED = re.compile(
    r"^(date\s|base\s|(no\s+)?internal\s+events\s+logged|//|begin\s+triggerblock"
    r"|end\s+triggerblock|\d+(\.\d+)?\s)",
    re.IGNORECASE,
)
# PEAK TRC: comment/header lines start with ';', messages with their number ("12)" in v1.x)
_TRC_ACCEPTED = re.compile(r"^(;|\d+\)?\s)")
_HEX = re.compile(r"[0-9A-Fa-f]*")
_CAN_ERR_FLAG = 0x20000000
_CAN_ERR_BUSERROR = 0x80  # with the error flag: what python-can reads as an error frame


def _matches(pattern: re.Pattern[str]) -> Callable[[str], None]:
    def check(line: str) -> None:
        if not pattern.match(line):
            raise ValueError(f"not a log line: {line[:40]!r}")

    return check


def _check_candump(line: str) -> None:
    """Refuse what python-can's .log reader would silently change: an odd number of data
    digits (it reads `D43` as D4 03), an id that is not 3 or 8 hex digits or above 1FFFFFFF
    (it masks it), a remote frame's dlc that is not one digit 0-8."""
    fields = line.split()
    if len(fields) not in (3, 4) or "#" not in fields[2]:
        raise ValueError(f"not a candump line (TIME IFACE ID#DATA [R|T]): {line[:40]!r}")
    can_id, _, data = fields[2].partition("#")
    if len(can_id) not in (3, 8) or not _HEX.fullmatch(can_id):
        raise ValueError(f"CAN id {can_id!r} is not 3 (standard) or 8 (extended) hex digits")
    value = int(can_id, 16)
    error_frame = value & _CAN_ERR_FLAG and value & _CAN_ERR_BUSERROR
    if value > MAX_EXT_ID and not error_frame:
        raise ValueError(f"CAN id {can_id} is above 1FFFFFFF")
    if data.startswith("#"):  # CAN FD: one flags digit, then the data
        flags, data = data[1:2], data[2:]
        if not _HEX.fullmatch(flags) or not flags:
            raise ValueError(f"CAN FD frame {fields[2]!r} has no flags digit after '##'")
    if data[:1] in ("R", "r"):
        if data[1:] and not (len(data) == 2 and data[1] in "012345678"):
            raise ValueError(f"remote frame {fields[2]!r}: R takes one dlc digit 0-8")
    elif not _HEX.fullmatch(data):
        raise ValueError(f"data {data!r} is not hex")
    elif len(data) % 2:
        raise ValueError(f"data {data!r} has an odd number of hex digits")


_CHECKS: dict[str, Callable[[str], None]] = {
    ".asc": _matches(_ASC_ACCEPTED),
    ".trc": _matches(_TRC_ACCEPTED),
    ".log": _check_candump,
}


class LogError(HilError):
    """A CAN log that cannot be read or written: names the file and the line or record."""


class _NumberedLines:
    """A text file that counts the lines python-can's reader has taken from it."""

    def __init__(self, file: TextIO, check: Callable[[str], None] | None) -> None:
        self.file = file
        self.line = 0
        self.check = check
        self.closed = False
        self.unterminated = False  # the last line taken has no line end: the file's last

    def __iter__(self) -> _NumberedLines:
        return self

    def __next__(self) -> str:
        self.line += 1
        try:
            text = next(self.file)
        except StopIteration:
            self.line -= 1
            raise
        self.unterminated = not text.endswith("\n")
        stripped = text.strip()
        if self.check is not None and stripped:
            self.check(stripped)
        return text

    def readline(self) -> str:
        try:
            return next(self)
        except StopIteration:
            return ""

    def close(self) -> None:
        self.closed = True
        self.file.close()


def suffix_of(path: Path) -> str:
    """The format suffix of a log path (`.gz` compression is not supported)."""
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        known = " ".join(SUFFIXES)
        raise LogError(f"{path}: unknown log format {path.suffix or '(no suffix)'!r}; use {known}")
    return suffix


NO_DIRECTION = "python-can's CSV has no direction column"
DIRECTED = ".log, .asc, .blf or .trc"  # the formats with one that softhil writes and reads


def has_direction(path: Path | str) -> bool:
    """Whether a log of `path`'s suffix records each frame's direction (R received, T sent): a
    .csv does not, so the controller's frames cannot be told from the plant's."""
    return Path(path).suffix.lower() != ".csv"


def check_format_available(path: Path, action: str = "writing") -> None:
    """LogError unless the optional package `path`'s format needs is installed: .mf4 needs
    asammdf (python-can's MF4 reader and writer only fail once used, with a traceback)."""
    if suffix_of(path) != ".mf4":
        return
    try:
        import asammdf  # noqa: F401
    except ImportError:
        raise LogError(f"{path}: {action} .mf4 needs asammdf (pip install asammdf)") from None


def _check_message(msg: can.Message) -> None:
    limit = MAX_EXT_ID if msg.is_extended_id else MAX_STD_ID
    if not 0 <= msg.arbitration_id <= limit and not msg.is_error_frame:
        raise ValueError(f"CAN id 0x{msg.arbitration_id:X} out of range")
    if not msg.is_fd and msg.dlc > 8:
        raise ValueError(f"{msg.dlc} data bytes in a classic CAN frame")
    # python-can's readers keep a dlc the data does not fill (.asc `d 5 10 27`)
    if not (msg.is_fd or msg.is_remote_frame or msg.is_error_frame) and msg.dlc != len(msg.data):
        raise ValueError(f"dlc {msg.dlc} but {len(msg.data)} data bytes")


def warn_stderr(text: str) -> None:
    """Where the reader's warnings go by default: one `hil: warning:` line on stderr."""
    print(f"hil: warning: {text}", file=sys.stderr)


def iter_log(path: Path | str, warn: Callable[[str], None] = warn_stderr) -> Iterator[can.Message]:
    """The messages of a log one by one; malformed input raises `LogError` (file and where).

    A .blf cut short (a crash or a full disk while recording) yields the frames of its complete
    objects before the cut, then `warn`s once naming the file and how many frames were read; it
    is an error only if no frame is readable. A text log cut inside its last line (no line end,
    the line malformed) reads the same way, warning once; one cut at a line end reads silently
    (nothing there says it was cut); a malformed line anywhere else is an error at that line.
    """
    path = Path(path)
    reading = _Reading(path, _readable(path))
    failure = ""
    try:
        yield from reading.frames()
        reading.finish(warn)
    except Exception as exc:  # python-can's readers raise anything on bad input
        if reading.cut_in_last_line():
            # the last line, malformed and without its line end: the writer stopped in it
            warn(
                f"{path}: line {reading.line} cut short (no line end, malformed): read the "
                f"{reading.count} frames before it; whatever was logged after them is lost"
            )
            return
        failure = reading.failure(exc)
        if reading.suffix != ".mf4":
            raise LogError(failure) from exc
        exc.__traceback__ = None  # asammdf objects in it complain when collected
    finally:
        reading.close()
    if failure:
        _collect_quietly()
        raise LogError(failure)
    if reading.count == 0:
        raise LogError(f"{path}: empty log (no CAN frames)")


def _readable(path: Path) -> str:
    """The suffix of a log `iter_log` can start reading: LogError for an unknown suffix, a
    missing file, a format whose optional package is missing, or an empty file."""
    suffix = suffix_of(path)
    if not path.is_file():
        raise LogError(f"{path}: no such log file")
    check_format_available(path, "reading")
    if path.stat().st_size == 0:  # in every format (a binary reader would want its header)
        raise LogError(f"{path}: empty log (no CAN frames)")
    return suffix


class _Reading:
    """One pass of `iter_log` over a log: python-can's reader for its format (a text one fed
    the counted lines), the frames yielded so far, and how a .blf was cut (else None)."""

    def __init__(self, path: Path, suffix: str) -> None:
        self.path = path
        self.suffix = suffix
        self.count = 0
        self.lines: _NumberedLines | None = None
        self.reader: can.io.generic.MessageReader | None = None
        self.cut: str | None = None

    @property
    def line(self) -> int:
        """The line the text reader has taken last (0 before the first, or for a binary log)."""
        return self.lines.line if self.lines is not None else 0

    def open(self) -> can.io.generic.MessageReader:
        """python-can's reader of the log's format."""
        if self.suffix in TEXT_SUFFIXES:
            text = self.path.open(encoding="utf-8", errors="strict", newline=None)
            self.lines = _NumberedLines(text, _CHECKS.get(self.suffix))
            # python-can's text readers take an open file; ours counts its lines
            readers = can.io.player.MESSAGE_READERS
            self.reader = readers[self.suffix](self.lines)  # type: ignore[arg-type]
        else:
            self.reader, self.cut = _binary_reader(self.path, self.suffix)
        return self.reader

    def frames(self) -> Iterator[can.Message]:
        """The log's frames, each checked, up to its end or to where a .blf was cut."""
        reader = self.open()
        with reader:
            frames = iter(reader)
            while True:
                try:
                    msg = next(frames)
                except StopIteration:
                    break
                except Exception:
                    # python-can stops on an object header the cut split; anything else than
                    # the end of the file is corruption, an error as ever
                    cut_reached = isinstance(reader, can.BLFReader) and (
                        reader.file.tell() >= self.path.stat().st_size
                    )
                    if self.cut is None or not cut_reached:
                        raise
                    break
                _check_message(msg)
                self.count += 1
                yield msg

    def finish(self, warn: Callable[[str], None]) -> None:
        """After the last frame: `warn` of a .blf cut after some frames; an error if none."""
        if self.cut is not None and self.count:
            expected = getattr(self.reader, "object_count", 0)
            counted = f" (the header counts {expected} objects)" if expected > self.count else ""
            warn(
                f"{self.path}: truncated or never closed ({self.cut}): read the {self.count} "
                f"frames before the end{counted}; whatever was logged after them is lost"
            )
        elif self.cut is not None:
            raise ValueError(f"truncated: {self.cut}, no complete frame before the cut")

    def cut_in_last_line(self) -> bool:
        """Whether a text log failed in its last line, one without a line end, after frames."""
        return self.lines is not None and self.lines.unterminated and self.count > 0

    def failure(self, exc: Exception) -> str:
        """The LogError text of `exc`: the file, where (line, record or header) and why."""
        if self.lines is not None:
            where = f"line {self.lines.line}"
        else:
            where = f"record {self.count + 1}" if self.reader is not None else "file header"
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return f"{self.path}: {where}: malformed {self.suffix} log ({reason})"

    def close(self) -> None:
        """Close the counted lines of a text log (python-can's reader leaves them open)."""
        if self.lines is not None and not self.lines.closed:
            self.lines.close()


def _collect_quietly() -> None:
    """Collect a half-built asammdf reader now, whose __del__ fails noisily on a bad file."""
    previous = sys.unraisablehook
    sys.unraisablehook = lambda _: None
    try:
        gc.collect()
    finally:
        sys.unraisablehook = previous


def _binary_reader(path: Path, suffix: str) -> tuple[can.io.generic.MessageReader, str | None]:
    """python-can's reader for the file, and how a .blf's size disagrees with its header (a
    file cut short, or never closed: BLFWriter writes the size when it stops), else None."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(8)
    if suffix == ".mf4" and head != b"MDF     ":
        raise ValueError("not an MDF file (bad magic)")
    reader = can.LogReader(str(path))
    if isinstance(reader, can.BLFReader) and reader.file_size != size:
        return reader, f"the header says {reader.file_size} bytes, the file has {size}"
    return reader, None


def read_log(path: Path | str, warn: Callable[[str], None] = warn_stderr) -> list[can.Message]:
    """Every message of a log, read completely before anything is done with them."""
    return list(iter_log(path, warn))


def open_writer(path: Path) -> can.io.generic.MessageWriter:
    """A python-can writer for `path`'s suffix (`.mf4` needs the optional asammdf)."""
    check_format_available(path)
    if not path.parent.is_dir():
        raise LogError(f"{path}: no such folder {path.parent}")
    try:
        writer = can.Logger(str(path))
    except ImportError as exc:
        raise LogError(f"{path}: writing {path.suffix} needs {exc.name or 'an extra'}") from exc
    except (OSError, ValueError) as exc:
        raise LogError(f"{path}: cannot write: {exc}") from exc
    if isinstance(writer, can.TRCWriter):  # its header names the file, not the folder
        writer.filepath = path.name
    return writer


def finish_writer(
    writer: can.io.generic.MessageWriter, path: Path, complete: bool, keep: bool = False
) -> None:
    """Flush and close the writer; remove the file unless it is complete, or `keep` (a live
    recording: frames that reached the file cannot be recorded again)."""
    try:
        writer.stop()
    except Exception as exc:
        complete = False
        kept = "; what was written is kept" if keep else ""
        raise LogError(f"{path}: cannot finish writing: {exc}{kept}") from exc
    finally:
        if not complete and not keep:
            with contextlib.suppress(OSError):
                path.unlink()


def write_log(path: Path | str, messages: Iterable[can.Message], overwrite: bool = True) -> int:
    """Write messages to a log by suffix; returns how many. The file appears only complete."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise LogError(f"{path}: exists; pass --overwrite to replace it")
    writer = open_writer(path)
    count = 0
    complete = False
    try:
        for msg in messages:
            writer.on_message_received(msg)
            count += 1
        complete = True
    finally:
        finish_writer(writer, path, complete)
    return count
