"""Benchmark: this checkout against another commit, as ratios from one run.

Both checkouts run the same closed loop, the default task on N segments (6 by default) for a
few simulated seconds, with `hil run` in a fresh interpreter each time: in-process (plant and
controller in one thread, direct bus) and across processes (the controller a separate program
over the loopback hub). The runs alternate (before, after, before, after, ...) so that a slow
stretch of a shared host falls on both; reported per mode: each checkout's median wall time per
SYNC of the loop (`summary.json`'s `wall_time`, the controller's start-up apart) and the ratio
after / before (below 1: faster now). Then each checkout's own per-SYNC budget
(`bench/bench_run.py --budget-only`, its instrumented split of a 6-segment in-process SYNC into
layers), from which the recording's share of a SYNC before and after.

The other checkout is the commit's tree (`git archive`), run with `PYTHONPATH` at it and the
same FMU cache, so both use the same compiler and flags; this checkout is the working tree.
The defaults (7 runs of 10 simulated seconds, 1001 SYNCs) are the least that reads a ratio to a
few per cent on a shared 2-core virtual machine, where single runs of the same code spread by
15-20 % and a 3-second run's SYNCs never pass the counter's wrap or a full garbage collection.

    PYTHONPATH=. python bench/compare.py --before e271ff8 [--repeat 7] [--seconds 10]
    [--segments 6] [--no-budget] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tarfile
import tempfile
import tomllib
from io import BytesIO
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
# where the default scenario is, in either layout (robots' folders, or the older hil/scenarios)
DEFAULT_SCENARIOS = ("robots/planar_arm/scenarios/default.toml", "hil/scenarios/default.toml")


def export(revision: str, folder: Path) -> Path:
    """The tree of `revision` written to `folder`."""
    archive = subprocess.run(
        ["git", "archive", "--format=tar", revision], cwd=ROOT, capture_output=True, check=True
    ).stdout
    with tarfile.open(fileobj=BytesIO(archive)) as tar:
        tar.extractall(folder, filter="data")
    return folder


def scenario(checkout: Path, segments: int, seconds: float, out: Path) -> Path:
    """The checkout's own default scenario on `segments` segments for `seconds`."""
    source = next(checkout / p for p in DEFAULT_SCENARIOS if (checkout / p).is_file())
    text = source.read_text(encoding="utf-8")
    text = re.sub(r"(?m)^segments = \d+$", f"segments = {segments}", text)
    text = re.sub(r"(?m)^duration = [0-9.]+$", f"duration = {seconds}", text)
    out.write_text(text, encoding="utf-8")
    return out


def run_once(checkout: Path, toml: Path, inprocess: bool, folder: Path) -> float:
    """One `hil run` of `toml` with `checkout`'s code: the loop's wall time per SYNC [us]."""
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    command = [sys.executable, "-m", "hil", "run", str(toml), "--out", str(folder)]
    command += ["--overwrite", "--no-progress"] + (["--inprocess"] if inprocess else [])
    subprocess.run(command, env=env, cwd=checkout, check=True, capture_output=True, timeout=600)
    summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    scenario = tomllib.loads(toml.read_text(encoding="utf-8"))
    syncs = round(scenario["duration"] / scenario["timing"]["control_period"]) + 1
    return float(summary["wall_time"]) / syncs * 1e6


def budget(checkout: Path) -> dict[str, Any]:
    """The checkout's own per-SYNC budget (bench_run.py --budget-only)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "budget.json"
        env = {**os.environ, "PYTHONPATH": str(checkout)}
        command = [sys.executable, "bench/bench_run.py", "--budget-only", "--json", str(out)]
        subprocess.run(command, env=env, cwd=checkout, check=True, capture_output=True)
        figures: dict[str, Any] = json.loads(out.read_text(encoding="utf-8"))
    found: dict[str, Any] = figures["budget"]
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", required=True, help="the commit to compare against")
    parser.add_argument("--repeat", type=int, default=7, help="runs per checkout and mode")
    parser.add_argument("--seconds", type=float, default=10.0, help="simulated seconds a run")
    parser.add_argument("--segments", type=int, default=6)
    parser.add_argument("--no-budget", action="store_true", help="skip the per-SYNC budgets")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = parser.parse_args()
    report: dict[str, Any] = {"before": args.before, "segments": args.segments}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        checkouts = {"before": export(args.before, work / "before"), "after": ROOT}
        tomls = {
            name: scenario(path, args.segments, args.seconds, work / f"{name}.toml")
            for name, path in checkouts.items()
        }
        for name in checkouts:  # a first run each builds and caches what it compiles
            run_once(checkouts[name], tomls[name], True, work / f"run-{name}")
        for mode, inprocess in (("in-process", True), ("across processes", False)):
            times: dict[str, list[float]] = {"before": [], "after": []}
            for i in range(args.repeat):
                for name in ("before", "after") if i % 2 == 0 else ("after", "before"):
                    folder = work / f"run-{name}"
                    times[name].append(run_once(checkouts[name], tomls[name], inprocess, folder))
            before, after = (statistics.median(times[n]) for n in ("before", "after"))
            report[mode] = {"us_per_sync": times, "ratio": after / before}
            print(
                f"{mode:17s} before {before:8.1f} us/SYNC  after {after:8.1f} us/SYNC  "
                f"ratio {after / before:.3f} (medians of {args.repeat})"
            )
        if not args.no_budget:
            for name, path in checkouts.items():
                figures = budget(path)
                share = figures["layers"]["recording"]["share"]
                report[f"budget {name}"] = figures
                print(f"recording's share of a SYNC, {name}: {100 * share:.1f} %")
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
