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

With --instructions it counts instead, under valgrind's callgrind (as bench/instructions.py),
the instructions of one pass's per-SYNC calls and of its closing: figures that do not move with
the load of a shared machine, as timings do by a factor of two.
"""

from __future__ import annotations

import argparse
import csv
import ctypes
import json
import math
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import can

import hil.recording
from hil.recording import CanLogger, SignalRecorder
from hil.rig import SignalSpec


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


def _no_toggle() -> None:
    pass


def one_pass(
    specs: list,
    rows: list,
    syncs: list,
    start: float,
    out: Path,
    wall: _Wall,
    toggles: tuple = (_no_toggle, _no_toggle),
) -> tuple[float, float]:
    """(seconds of the per-SYNC calls, seconds of closing) of one pass into `out`; the
    `toggles` are called around each (callgrind's collection, with --instructions)."""
    wall.now = 0.0
    signals = SignalRecorder(out / "signals.csv", specs)
    log = CanLogger(out / "can.log", start=start)
    clock = time.perf_counter
    toggles[0]()
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
    toggles[0]()
    toggles[1]()
    began = clock()
    signals.close()
    log.close()
    closing = clock() - began
    toggles[1]()
    return running, closing


TOGGLE_C = "#include <valgrind/callgrind.h>\nvoid toggle(void) { CALLGRIND_TOGGLE_COLLECT; }\n"


def counted(run: Path, part: str) -> int:
    """Instructions of one pass's per-SYNC calls (`part` "sync") or closing ("close")."""
    valgrind = shutil.which("valgrind")
    if valgrind is None:
        raise SystemExit("--instructions: valgrind is not installed (Debian: apt install valgrind)")
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONHASHSEED": "0"}
    command = [
        valgrind,
        "--tool=callgrind",
        "--collect-atstart=no",
        "--callgrind-out-file=/dev/null",
    ]
    command += [sys.executable, __file__, str(run), "--count", part]
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
    found = re.findall(r"==\d+== Collected : (\d+)", done.stderr)
    if done.returncode != 0 or not found:
        raise SystemExit(f"--instructions: the pass under callgrind failed: {done.stderr[-300:]}")
    return int(found[-1])


def _toggle_library(folder: Path) -> ctypes.CDLL:
    source = folder / "toggle.c"
    source.write_text(TOGGLE_C)
    library = folder / "toggle.so"
    compiler = os.environ.get("CC", "cc")
    subprocess.run(
        [compiler, "-O2", "-fPIC", "-shared", "-o", str(library), str(source)], check=True
    )
    return ctypes.CDLL(str(library))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="results folder of a run (signals.csv, can.log)")
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--json", type=Path)
    parser.add_argument(
        "--sync-us", type=float, default=400.0, help="wall time of a SYNC in the run [us]"
    )
    parser.add_argument("--instructions", action="store_true", help="count under callgrind")
    parser.add_argument("--count", choices=("sync", "close"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    specs, rows, syncs = load_run(args.run)
    first = next(iter(can.LogReader(str(args.run / "can.log")))).timestamp
    wall = _Wall(args.sync_us * 1e-6)
    hil.recording.time = wall  # type: ignore[assignment]
    if args.instructions:
        figures = {
            "rows": len(rows),
            "instructions_per_sync": counted(args.run, "sync") / len(rows),
            "close_instructions": counted(args.run, "close"),
        }
        print(json.dumps(figures))
        return 0
    if args.count:  # under callgrind: one pass, collected around the part counted
        with tempfile.TemporaryDirectory() as tmp:
            toggle = _toggle_library(Path(tmp)).toggle
            toggles = (toggle, _no_toggle) if args.count == "sync" else (_no_toggle, toggle)
            one_pass(specs, rows, syncs, first, Path(tmp), wall, toggles)
        return 0
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
