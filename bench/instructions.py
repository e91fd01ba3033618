"""Instructions per SYNC of the closed loop, counted by callgrind: a figure that does not drift.

On a noisy virtual machine wall-clock figures of the same code move by 20-30 % from hour to hour,
so two versions of the loop that differ by less cannot be told apart by timing them. callgrind
counts the instructions the loop executes, the same on every run of the same code: compare two
versions by running this in each checkout.

It runs the benchmark scenario of `bench_run.budget_scenario` (the default task on N segments,
in-process) under ``valgrind --tool=callgrind --collect-atstart=no``, with one OpenBLAS thread
(its spinning worker threads add a varying count) and a fixed hash seed. Collection is switched
on when the plant's loop starts (`Plant.run_driven`) and off when it returns, through callgrind's
client request CALLGRIND_TOGGLE_COLLECT (a few lines of C built with the package's compiler), so
start-up, FMU loading, the summary, the estimation report and the plots are not counted. Needs
valgrind and its headers (Debian's `valgrind` package). A 0.5 s run takes a few minutes.

Run from the checkout: PYTHONPATH=. python bench/instructions.py [--segments 6] [--seconds 0.5]
[--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

TOGGLE_C = """#include <valgrind/callgrind.h>
void softhil_toggle_collect(void) { CALLGRIND_TOGGLE_COLLECT; }
"""
COLLECTED = re.compile(r"==\d+== Collected : (\d+)")


def instructions_per_sync(valgrind_stderr: str, syncs: int) -> float:
    """Instructions per SYNC from callgrind's "Collected : N" line and the loop's SYNCs."""
    found = COLLECTED.findall(valgrind_stderr)
    if not found:
        raise ValueError("callgrind printed no 'Collected' line")
    if syncs <= 0:
        raise ValueError(f"the loop ran {syncs} SYNCs")
    return int(found[-1]) / syncs


def _inner(segments: int, seconds: float) -> int:
    """Under callgrind: run the scenario with collection on for the loop only; its SYNCs."""
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_run import ROOT, budget_scenario, shared_library

    from hil.plant import Plant
    from hil.run import RunOptions, run_scenario
    from hil.scenario import load_scenario

    library = shared_library("callgrind_toggle", TOGGLE_C, ("-O2", "-fPIC", "-shared"))
    toggle = library.softhil_toggle_collect
    run_driven = Plant.run_driven

    def counted(plant: Plant, *args: Any, **kwargs: Any) -> Any:
        toggle()
        try:
            return run_driven(plant, *args, **kwargs)
        finally:
            toggle()

    Plant.run_driven = counted  # type: ignore[method-assign,assignment]
    scenario = budget_scenario(
        load_scenario(ROOT / "robots" / "planar_arm" / "scenarios" / "default.toml"),
        seconds,
        segments,
    )
    with tempfile.TemporaryDirectory() as out:
        run_scenario(scenario, RunOptions(out=Path(out), inprocess=True, progress=False))
    return scenario.cycles + 1  # SYNC 0..cycles


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--segments", type=int, default=6)
    parser.add_argument("--seconds", type=float, default=0.5, help="simulated time")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.inner:
        print(f"SYNCS {_inner(args.segments, args.seconds)}")
        return 0
    valgrind = shutil.which("valgrind")
    if valgrind is None:
        print("instructions: valgrind is not installed (Debian: apt install valgrind)")
        return 2
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONHASHSEED": "0"}
    command = [valgrind, "--tool=callgrind", "--collect-atstart=no"]
    command += ["--callgrind-out-file=/dev/null", sys.executable, __file__, "--inner"]
    command += ["--segments", str(args.segments), "--seconds", str(args.seconds)]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    syncs = re.findall(r"^SYNCS (\d+)$", done.stdout, re.MULTILINE)
    if done.returncode != 0 or not syncs:
        tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
        print(f"instructions: the run under callgrind failed: {tail}")
        return 1
    per_sync = instructions_per_sync(done.stderr, int(syncs[-1]))
    print(
        f"closed loop, {args.segments} segments in-process, {int(syncs[-1])} SYNCs: "
        f"{per_sync / 1e6:.3f} million instructions per SYNC"
    )
    if args.json:
        figures = {"segments": args.segments, "syncs": int(syncs[-1]), "per_sync": per_sync}
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
