"""Benchmark: the recorders alone (hil.recording), fed a recorded run's rows and frames.

A run's `signals.csv` and candump `can.log` are read back into what the plant hands the
recorders at each SYNC: the sourced values of a row (`begin_row`), the cells frames fill
(`set_cells`: the columns whose cells are integers here, the controller's reports), the frames
it received one by one (`log`) and those it sent together (`log_all`), and a `flush` a SYNC.
The recorders' wall clock advances --sync-us a SYNC (the 6-segment loop's 400 us by default),
so they flush and write blocks every FLUSH_INTERVAL as in a run. Reported: microseconds a SYNC
for those calls (the recording's share of a SYNC), and the closing (`close` of both: the last
writes and, since the blocks, the CSV made from them), each the median of --repeat passes. The
files written are compared with the run's, byte for byte (the run's own CSV and log are the
reference).

To compare two commits, run it from each checkout in turn, interleaved, on the same run:

    PYTHONPATH=. python bench/bench_recording.py runs/planar-grasp-1 [--repeat 7] [--json f]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import can

import hil.recording
from hil.recording import CanLogger, SignalRecorder
from hil.robots import SignalSpec


class _Wall:
    """The recorders' wall clock (`time.monotonic`) advanced `period` a SYNC: their flushes
    and blocks come every FLUSH_INTERVAL as in a run that takes `period` a SYNC."""

    def __init__(self, period: float) -> None:
        self.period = period
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now

    def perf_counter(self) -> float:
        return time.perf_counter()


def load_run(folder: Path) -> tuple[list[SignalSpec], list[tuple], list[list[tuple]]]:
    """(specs, rows, frames by SYNC) of a run (`load_rows`, `load_frames`)."""
    return (*load_rows(folder / "signals.csv"), load_frames(folder / "can.log"))


def load_rows(path: Path) -> tuple[list[SignalSpec], list[tuple]]:
    """(specs, rows) of a signals CSV: a row is (time, sourced values, cells), the cells those
    of the columns whose every cell is an integer or empty (the controller's reports)."""
    with path.open(newline="") as file:
        table = list(csv.reader(file))
    header, body = table[0], table[1:]
    integer = [
        all(c == "" or c.lstrip("-").isdigit() for c in column)
        for column in zip(*body, strict=True)
    ]
    specs = [
        SignalSpec(name, "", "", frame=("Bench", 0, name))
        if is_int
        else SignalSpec(name, "", "", source=f"p.{name}")
        for name, is_int in zip(header[1:], integer[1:], strict=True)
    ]
    rows = []
    for row in body:
        sourced = tuple(
            float(c) if c else math.nan
            for c, is_int in zip(row[1:], integer[1:], strict=True)
            if not is_int
        )
        cells = [
            (name, int(c))
            for name, c, is_int in zip(header[1:], row[1:], integer[1:], strict=True)
            if is_int and c
        ]
        rows.append((float(row[0]), sourced, cells))
    return specs, rows


def load_frames(path: Path) -> list[list[tuple]]:
    """The frames of a candump log by SYNC: SYNC k's are the groups (time from the log's first
    stamp, received, [messages]) from its SYNC frame on, as the plant logged them."""
    start = None
    syncs: list[list[tuple]] = [[]]
    for message in can.LogReader(str(path)):
        if start is None:
            start = message.timestamp
        if message.arbitration_id == 0x080 and message.is_rx and syncs[-1]:
            syncs.append([])
        group = syncs[-1]
        plain = can.Message(
            arbitration_id=message.arbitration_id,
            is_extended_id=message.is_extended_id,
            data=message.data,
        )
        stamp = round(message.timestamp - start, 6)
        if group and group[-1][0] == stamp and group[-1][1] == message.is_rx:
            group[-1][2].append(plain)
        else:
            group.append((stamp, message.is_rx, [plain]))
    return syncs


def one_pass(
    specs: list, rows: list, syncs: list, start: float, out: Path, wall: _Wall
) -> tuple[float, float]:
    """(seconds of the per-SYNC calls, seconds of closing) of one pass into `out`."""
    wall.now = 0.0
    signals = SignalRecorder(out / "signals.csv", specs)
    log = CanLogger(out / "can.log", start=start)
    clock = time.perf_counter
    began = clock()
    for k, (t, sourced, cells) in enumerate(rows):
        for at, received, messages in syncs[k] if k < len(syncs) else ():
            if received:
                for message in messages:
                    log.log(message, at, True)
            else:
                log.log_all(messages, at, False)
        signals.begin_row(t, sourced)
        signals.set_cells(cells)  # the controller's reports, received in the period after
        log.flush()
        wall.now += wall.period
    for late in syncs[len(rows) :]:
        for at, received, messages in late:
            log.log_all(messages, at, received)
    running = clock() - began
    began = clock()
    signals.close()
    log.close()
    return running, clock() - began


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="results folder of a run (signals.csv, can.log)")
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--json", type=Path)
    parser.add_argument(
        "--sync-us", type=float, default=400.0, help="wall time of a SYNC in the run [us]"
    )
    args = parser.parse_args()
    specs, rows, syncs = load_run(args.run)
    first = next(can.LogReader(str(args.run / "can.log"))).timestamp
    wall = _Wall(args.sync_us * 1e-6)
    hil.recording.time = wall  # type: ignore[attr-defined]
    runs, closes = [], []
    for _ in range(args.repeat):
        with tempfile.TemporaryDirectory() as tmp:
            running, closing = one_pass(specs, rows, syncs, first, Path(tmp), wall)
            same = all(
                (Path(tmp) / name).read_bytes() == (args.run / name).read_bytes()
                for name in ("signals.csv", "can.log")
            )
        if not same:
            print("the files differ from the run's", file=sys.stderr)
            return 1
        runs.append(running / len(rows) * 1e6)
        closes.append(closing * 1e3)
    frames = sum(len(m) for sync in syncs for _, _, m in sync) / len(rows)
    report = {
        "rows": len(rows),
        "columns": len(specs) + 1,
        "frames_per_sync": frames,
        "us_per_sync": statistics.median(runs),
        "close_ms": statistics.median(closes),
    }
    print(json.dumps(report))
    if args.json:
        args.json.write_text(json.dumps(report) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
