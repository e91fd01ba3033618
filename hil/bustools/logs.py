"""Reading and writing CAN logs in every format python-can knows, chosen by file suffix.

`read_log` turns every malformed input (an unknown suffix, an empty log, a garbage line, a
truncated or random-byte binary file) into one `LogError` naming the file and where: the line
number of text formats, the record number of binary ones. `write_log` writes by suffix through
`can.Logger` and removes the file again if writing fails, so a failure never leaves a
half-written log behind under the requested name.
"""

from __future__ import annotations

import contextlib
import gc
import re
import sys
from collections.abc import Iterable, Iterator
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
_CHECKS = {".asc": _ASC_ACCEPTED, ".trc": _TRC_ACCEPTED}


class LogError(HilError):
    """A CAN log that cannot be read or written: names the file and the line or record."""


class _NumberedLines:
    """A text file that counts the lines python-can's reader has taken from it."""

    def __init__(self, file: TextIO, check: re.Pattern[str] | None) -> None:
        self.file = file
        self.line = 0
        self.check = check
        self.closed = False

    def __iter__(self) -> _NumberedLines:
        return self

    def __next__(self) -> str:
        self.line += 1
        try:
            text = next(self.file)
        except StopIteration:
            self.line -= 1
            raise
        stripped = text.strip()
        if self.check is not None and stripped and not self.check.match(stripped):
            raise ValueError(f"not a log line: {stripped[:40]!r}")
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


def _check_message(msg: can.Message) -> None:
    limit = MAX_EXT_ID if msg.is_extended_id else MAX_STD_ID
    if not 0 <= msg.arbitration_id <= limit and not msg.is_error_frame:
        raise ValueError(f"CAN id 0x{msg.arbitration_id:X} out of range")
    if not msg.is_fd and msg.dlc > 8:
        raise ValueError(f"{msg.dlc} data bytes in a classic CAN frame")


def iter_log(path: Path | str) -> Iterator[can.Message]:
    """The messages of a log one by one; malformed input raises `LogError` (file and where)."""
    path = Path(path)
    suffix = suffix_of(path)
    if not path.is_file():
        raise LogError(f"{path}: no such log file")
    if suffix == ".mf4":
        try:
            import asammdf  # noqa: F401
        except ImportError:
            raise LogError(
                f"{path}: reading .mf4 needs asammdf (pip install 'softhil[mf4]')"
            ) from None
    count = 0
    lines: _NumberedLines | None = None
    reader: can.io.generic.MessageReader | None = None
    failure = ""
    try:
        if suffix in TEXT_SUFFIXES:
            text = path.open(encoding="utf-8", errors="strict", newline=None)
            lines = _NumberedLines(text, _CHECKS.get(suffix))
            # python-can's text readers take an open file; ours counts its lines
            reader = can.io.player.MESSAGE_READERS[suffix](lines)  # type: ignore[arg-type]
        else:
            reader = _binary_reader(path, suffix)
        with reader:
            for msg in reader:
                _check_message(msg)
                count += 1
                yield msg
    except Exception as exc:  # python-can's readers raise anything on bad input
        if lines is not None:
            where = f"line {lines.line}"
        else:
            where = f"record {count + 1}" if reader is not None else "file header"
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        failure = f"{path}: {where}: malformed {suffix} log ({reason})"
        if suffix != ".mf4":
            raise LogError(failure) from exc
        exc.__traceback__ = None  # asammdf objects in it complain when collected
    finally:
        if lines is not None and not lines.closed:
            lines.close()
    if failure:
        _collect_quietly()
        raise LogError(failure)
    if count == 0:
        raise LogError(f"{path}: empty log (no CAN frames)")


def _collect_quietly() -> None:
    """Collect a half-built asammdf reader now, whose __del__ fails noisily on a bad file."""
    previous = sys.unraisablehook
    sys.unraisablehook = lambda _: None
    try:
        gc.collect()
    finally:
        sys.unraisablehook = previous


def _binary_reader(path: Path, suffix: str) -> can.io.generic.MessageReader:
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(8)
    if suffix == ".mf4" and head != b"MDF     ":
        raise ValueError("not an MDF file (bad magic)")
    reader = can.LogReader(str(path))
    if isinstance(reader, can.BLFReader) and reader.file_size != size:
        reader.stop()
        raise ValueError(
            f"truncated: the header says {reader.file_size} bytes, the file has {size}"
        )
    return reader


def read_log(path: Path | str) -> list[can.Message]:
    """Every message of a log, read completely before anything is done with them."""
    return list(iter_log(path))


def open_writer(path: Path) -> can.io.generic.MessageWriter:
    """A python-can writer for `path`'s suffix (`.mf4` needs the optional asammdf)."""
    suffix_of(path)
    if not path.parent.is_dir():
        raise LogError(f"{path}: no such folder {path.parent}")
    try:
        return can.Logger(str(path))
    except ImportError as exc:
        raise LogError(f"{path}: writing {path.suffix} needs {exc.name or 'an extra'}") from exc
    except (OSError, ValueError) as exc:
        raise LogError(f"{path}: cannot write: {exc}") from exc


def finish_writer(writer: can.io.generic.MessageWriter, path: Path, complete: bool) -> None:
    """Flush and close the writer; remove the file unless it is complete."""
    try:
        writer.stop()
    except Exception as exc:
        complete = False
        raise LogError(f"{path}: cannot finish writing: {exc}") from exc
    finally:
        if not complete:
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
