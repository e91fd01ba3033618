"""`hil bus dump`: one candump-style line per frame, decoded with the DBC.

Each line is the candump -L text of the frame (so `--raw` output is itself a `.log` file)
followed, unless `--raw`, by the DBC message name and its signals with units, e.g.
`(0.010000) can0 181#D430000000000001 T  DriveStatus1 piston_position=0.025 m ... counter=1`.
Frames whose id the DBC does not know are shown raw, marked `?`, and counted by id. The count
line goes to stderr at the end, also after Ctrl-C.
"""

from __future__ import annotations

import sys
import time
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TextIO

import can
from cantools.database.can import Database

from hil.bustools.frames import FrameFilter, candump_text, dbc_message, decoded


def _value_text(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def describe(database: Database, msg: can.Message) -> tuple[str, bool]:
    """(decoded text, known) of a frame: `Name sig=value unit ...`, or `?` for unknown ids."""
    message = dbc_message(database, msg)
    if message is None:
        return "?", False
    if len(msg.data) != message.length:
        return f"{message.name} ? {len(msg.data)} bytes, the DBC says {message.length}", True
    values = decoded(message, msg)
    parts = []
    for signal in message.signals:
        unit = f" {signal.unit}" if signal.unit else ""
        value = values[signal.name]
        # the DBC's name for the value, as cantools decode shows it (a bit field's other values
        # have none): nmt_state=5 (operational)
        named = signal.choices.get(value) if signal.choices and value == int(value) else None
        text = f"{_value_text(value)} ({named})" if named is not None else _value_text(value)
        parts.append(f"{signal.name}={text}{unit}")
    return f"{message.name} " + " ".join(parts), True


@dataclass
class DumpCount:
    shown: int = 0
    decoded: int = 0
    unknown: Counter[int] = field(default_factory=Counter)
    raw: bool = False  # shown undecoded (--raw): `decoded` counts the ids the DBC knows
    passed: int = 0  # frames read that --id / --message did not select

    def line(self) -> str:
        known = "known to the DBC" if self.raw else "decoded"
        text = f"{self.shown} frame{'s' * (self.shown != 1)}, {self.decoded} {known}"
        if self.unknown:
            ids = ", ".join(f"0x{i:03X} x{n}" for i, n in sorted(self.unknown.items()))
            text += f", {sum(self.unknown.values())} unknown ({ids})"
        if self.passed:
            text += f"; {self.passed} not selected by --id/--message"
        return text


def dump(
    frames: Iterable[can.Message],
    database: Database,
    selection: FrameFilter,
    raw: bool,
    count: int | None,
    out: TextIO,
    tally: DumpCount | None = None,
    direction: bool = True,
) -> DumpCount:
    """Print the selected frames; stops after `count` of them or at the end of `frames`.
    Counts into `tally` as it goes, so a caller that is interrupted still has the counts.
    `direction` False: the frames come from a log without one (.csv), no R/T is shown."""
    tally = DumpCount() if tally is None else tally
    for msg in frames:
        if count is not None and tally.shown >= count:
            break
        if not selection.matches(msg):
            tally.passed += 1
            continue
        channel = "can0" if msg.channel is None else str(msg.channel)
        if channel.isdigit():  # a .blf/.asc/.trc channel number: named as python-can's
            channel = f"can{channel}"  # CanutilsLogWriter (logconvert to .log) names it
        line = candump_text(msg, channel, direction)
        text, known = describe(database, msg)
        if known:
            tally.decoded += 1
        else:
            tally.unknown[msg.arbitration_id] += 1
        print(line if raw else f"{line}  {text}", file=out, flush=True)
        tally.shown += 1
        if count is not None and tally.shown >= count:
            break
    return tally


PROBE_INTERVAL = 1.0  # [s] between two probes of a quiet bus's hub


def live_frames(bus: can.BusABC, idle_timeout: float | None) -> Iterable[can.Message]:
    """Frames from a bus until `idle_timeout` seconds pass without one (None: forever)."""
    from rigbus.canbus import connection_closed

    last = probed = time.monotonic()
    while True:
        msg = bus.recv(0.2 if idle_timeout is None else min(0.2, idle_timeout))
        now = time.monotonic()
        if msg is not None:
            last = now
            yield msg
            continue
        # is the hub still there? At most once a second: each probe is a connection to the
        # hub, which a full hub refuses and logs
        if now - probed >= PROBE_INTERVAL:
            probed = now
            if connection_closed(bus):
                return
        if idle_timeout is not None and now - last >= idle_timeout:
            return


def print_count(tally: DumpCount) -> None:
    print(tally.line(), file=sys.stderr)
