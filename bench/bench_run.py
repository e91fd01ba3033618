"""Benchmark: real-time factor of the default scenario and the cost of a macro step.

Every figure is a ratio against a baseline measured in the same process and run: fmpy stepping
the same two FMUs alone (inputs and outputs transferred by value reference, no master, no bus).
Layers measured on top of it, all for the same simulated time:
  master        the co-simulation master stepping the same FMUs (connections, observers)
  inprocess     `hil run --inprocess`: master + plant node + controller thread, virtual bus
  process       `hil run`: controller as a separate process over the loopback hub

Run: python bench/bench_run.py [--repeat 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from hil.fmu.slave import FmuSlave
from hil.master import Master
from hil.robots import build_rig
from hil.run import RunOptions, run_scenario
from hil.scenario import Scenario, load_scenario


def baseline(scenario: Scenario) -> float:
    """fmpy alone: step DriveCylinder and FeaSegment with the same coupling, no framework."""
    cylinder = FmuSlave("DriveCylinder", "cylinder1")
    segment = FmuSlave("FeaSegment", "segment1")
    vr = {name: cylinder.value_reference(name) for name in ("x", "p_a", "p_b")}
    sv = {name: segment.value_reference(name) for name in ("x_piston", "p_a", "p_b")}
    h = scenario.timing.step
    ticks = round(scenario.duration / h)
    start = time.perf_counter()
    x, pa, pb = 0.025, 0.0, 0.0
    for k in range(ticks):
        cylinder.set_reals([vr["p_a"], vr["p_b"]], [pa, pb])
        segment.set_reals([sv["x_piston"]], [x])
        cylinder.do_step(k * h, h)
        segment.do_step(k * h, h)
        (x,) = cylinder.get_reals([vr["x"]])
        pa, pb = segment.get_reals([sv["p_a"], sv["p_b"]])
    elapsed = time.perf_counter() - start
    cylinder.close()
    segment.close()
    return elapsed


def master_only(scenario: Scenario) -> float:
    rig = build_rig(scenario)
    master = Master(rig.participants, rig.connections, scenario.timing.step)
    start = time.perf_counter()
    master.advance_to(round(scenario.duration / scenario.timing.step))
    elapsed = time.perf_counter() - start
    rig.close()
    return elapsed


def full_run(scenario: Scenario, inprocess: bool) -> float:
    with tempfile.TemporaryDirectory() as out:
        result = run_scenario(
            scenario, RunOptions(out=Path(out), inprocess=inprocess, progress=False)
        )
        return float(result.summary["wall_time"])


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeat", type=int, default=3, help="runs per layer (median taken)")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = parser.parse_args()
    scenario = load_scenario()
    scenario = replace(scenario, bus=replace(scenario.bus, kind="loopback", port=0))
    layers = {
        "baseline (fmpy alone)": lambda: baseline(scenario),
        "master": lambda: master_only(scenario),
        "hil run --inprocess": lambda: full_run(scenario, inprocess=True),
        "hil run (separate process)": lambda: full_run(scenario, inprocess=False),
    }
    baseline(scenario)  # warm up: build/load the FMUs once
    medians = {
        name: statistics.median(f() for _ in range(args.repeat)) for name, f in layers.items()
    }
    ticks = round(scenario.duration / scenario.timing.step)
    fmus = 2 * scenario.robot.segments
    base = medians["baseline (fmpy alone)"]
    print(
        f"default scenario: {scenario.duration:g} s simulated, {ticks} macro steps of "
        f"{fmus} FMUs, median of {args.repeat}"
    )
    print(f"{'layer':28s} {'wall [s]':>9s} {'RTF':>7s} {'us/FMU step':>12s} {'x baseline':>11s}")
    rows = {}
    for name, wall in medians.items():
        per_step = wall / (ticks * fmus) * 1e6
        rows[name] = {
            "wall_time": wall,
            "real_time_factor": scenario.duration / wall,
            "us_per_fmu_step": per_step,
            "ratio_to_baseline": wall / base,
        }
        print(
            f"{name:28s} {wall:9.3f} {scenario.duration / wall:7.1f} {per_step:12.1f} "
            f"{wall / base:11.2f}"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
