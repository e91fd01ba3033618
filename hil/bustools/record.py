"""`hil bus record`: every frame of a bus into a log file of any python-can format by suffix.

The file is written through python-can's writer for its suffix (`can.Logger`), flushed and
closed in a `finally`, so Ctrl-C and SIGTERM (turned into KeyboardInterrupt while recording)
leave a complete, readable file. An existing file is refused unless `overwrite`; if writing
itself fails (a full disk), the frames written before stay in the file, since a live bus cannot
be recorded again, and the error says how many.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType

import can

from hil.bustools.dump import live_frames
from hil.bustools.logs import LogError, finish_writer, open_writer, suffix_of


@contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt in the main thread, so `finally` blocks run."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def record(
    bus: can.BusABC,
    path: Path,
    overwrite: bool = False,
    count: int | None = None,
    idle_timeout: float | None = None,
    on_ready: Callable[[], None] | None = None,
) -> int:
    """Record frames from `bus` into `path` until Ctrl-C/SIGTERM, `count` frames or
    `idle_timeout` seconds without a frame. Returns the number of frames written."""
    suffix_of(path)
    if path.exists() and not overwrite:
        raise LogError(f"{path}: exists; pass --overwrite to replace it")
    writer = open_writer(path)
    written = 0
    failure: OSError | None = None
    try:
        with sigterm_interrupts():
            try:
                if on_ready is not None:
                    on_ready()
                for msg in live_frames(bus, idle_timeout):
                    try:
                        writer.on_message_received(msg)
                    except OSError as exc:  # a full disk: keep what is written
                        failure = exc
                        break
                    written += 1
                    if count is not None and written >= count:
                        break
            except KeyboardInterrupt:
                pass  # the normal way to stop recording
    finally:
        finish_writer(writer, path, complete=False, keep=True)
    if failure is not None:
        raise LogError(
            f"{path}: cannot write frame {written + 1}: {failure.strerror or failure}; the "
            f"{written} frames before it are kept"
        )
    return written
