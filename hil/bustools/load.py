"""Bus load measured from frames (a log, or live traffic) rather than implied by a scenario.

Load = sum over frames of their bits on the wire / (span in seconds * bitrate), with the bits of
`rigbus.protocol.frame_bits` (worst-case bit stuffing); an extended id adds 20 frame bits
and their worst-case stuff bits (25 in all). The span is the time from the first to the last
frame (a log) or the listening time (live). Rates are frames / span.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import can
from cantools.database.can import Database

from hil.bustools.frames import dbc_message
from hil.errors import HilError
from rigbus.protocol import frame_bits

EXTENDED_EXTRA_BITS = 25


def wire_bits(msg: can.Message) -> int:
    dlc = 0 if msg.is_remote_frame else len(msg.data)
    return frame_bits(dlc) + (EXTENDED_EXTRA_BITS if msg.is_extended_id else 0)


@dataclass(frozen=True)
class MessageLoad:
    name: str
    frame_id: int
    extended: bool
    frames: int
    bits: int


@dataclass(frozen=True)
class LoadReport:
    span: float
    bitrate: int
    rows: list[MessageLoad]

    @property
    def load(self) -> float:
        return sum(r.bits for r in self.rows) / (self.span * self.bitrate)

    def lines(self) -> list[str]:
        total_bits = sum(r.bits for r in self.rows) or 1
        out = [
            f"bus load {100 * self.load:.1f} % at {self.bitrate / 1000:g} kbit/s over "
            f"{self.span:g} s (worst-case bit stuffing), {sum(r.frames for r in self.rows)} frames",
            f"{'message':<18} {'id':>10} {'frames':>8} {'rate Hz':>9} {'share %':>8}",
        ]
        for r in sorted(self.rows, key=lambda r: (r.extended, r.frame_id)):
            frame_id = f"0x{r.frame_id:08X}" if r.extended else f"0x{r.frame_id:03X}"
            out.append(
                f"{r.name:<18} {frame_id:>10} {r.frames:>8} {r.frames / self.span:>9.2f} "
                f"{100 * r.bits / total_bits:>8.1f}"
            )
        return out


def check_bitrate(bitrate: int) -> None:
    """Refuse a --bitrate that no classical CAN bus runs at."""
    from hil.scenario import MAX_BITRATE

    if not 0 < bitrate <= MAX_BITRATE:
        raise HilError(
            f"--bitrate: {bitrate} bit/s; classical CAN runs at 1..{MAX_BITRATE} bit/s (at most "
            "1 Mbit/s, ISO 11898-1)"
        )


def measure(
    frames: Iterable[can.Message], database: Database, bitrate: int, span: float | None = None
) -> LoadReport:
    """Per-message frames and bits; `span` None takes it from the first and last timestamp."""
    check_bitrate(bitrate)
    counts: dict[tuple[int, bool], list[int]] = {}
    names: dict[tuple[int, bool], str] = {}
    first = last = None
    for msg in frames:
        if msg.is_error_frame:
            continue
        key = (msg.arbitration_id, msg.is_extended_id)
        entry = counts.setdefault(key, [0, 0])
        entry[0] += 1
        entry[1] += wire_bits(msg)
        if key not in names:
            message = dbc_message(database, msg)
            names[key] = message.name if message is not None else "?"
        first = msg.timestamp if first is None else first
        last = msg.timestamp
    if span is None:
        if first is None or last is None or last <= first:
            raise HilError("bus load needs frames spanning some time (two distinct timestamps)")
        span = last - first
    if span <= 0:
        raise HilError("bus load needs a positive listening time")
    rows = [
        MessageLoad(names[key], key[0], key[1], frames, bits)
        for key, (frames, bits) in counts.items()
    ]
    return LoadReport(span, bitrate, rows)
