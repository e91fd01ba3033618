"""Benchmark: the spatial arm's closed loop in-process, as a real-time factor (simulated seconds
per wall second: the ratio the issue's 10x is stated in), with the wall time split between the
controller's estimator, its controller and the rest (the plant's FMUs, devices, bus, recording).

    PYTHONPATH=. python bench/spatial_speed.py [--duration 20] [--scenario spatial-point]

The first goal's IK and the first-use imports are outside the timed loop's share only as far as
they fall in it: the figure is the run's own, as `hil run` reports it.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="spatial-point")
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    from hil.run import RunOptions, run_scenario
    from hil.scenario import load_scenario, resolve_scenario
    from robots.spatial_arm.controller import control, estimator

    shares = {"estimator": 0.0, "controller": 0.0}

    def timed(cls: type, name: str, key: str) -> None:
        original = getattr(cls, name)

        def wrapper(self, *a, **k):  # type: ignore[no-untyped-def]
            t0 = time.perf_counter()
            try:
                return original(self, *a, **k)
            finally:
                shares[key] += time.perf_counter() - t0

        setattr(cls, name, wrapper)

    timed(estimator.SpatialEstimator, "update", "estimator")
    timed(control.SpatialControl, "compute", "controller")
    path = resolve_scenario(args.scenario)
    text = path.read_text()
    import re

    text = re.sub(r"(?m)^duration = .*$", f"duration = {args.duration}", text, count=1)
    with tempfile.TemporaryDirectory() as folder:
        scenario_path = Path(folder) / "s.toml"
        scenario_path.write_text(text)
        for k in range(args.repeat):
            shares.update(estimator=0.0, controller=0.0)
            scenario = load_scenario(scenario_path)
            out = Path(folder) / f"run{k}"
            t0 = time.perf_counter()
            result = run_scenario(scenario, RunOptions(out=out, inprocess=True, progress=False))
            wall = time.perf_counter() - t0
            loop = result.summary.get("wall_time") or wall
            rtf = result.summary.get("real_time_factor")
            print(
                f"{args.scenario} {args.duration:g} s: real-time factor {rtf:.2f} "
                f"(run incl. results {wall:.2f} s); estimator {shares['estimator']:.2f} s, "
                f"controller {shares['controller']:.2f} s, rest {loop - sum(shares.values()):.2f} s"
            )


if __name__ == "__main__":
    main()
