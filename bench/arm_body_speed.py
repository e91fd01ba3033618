"""Benchmark: one 1 ms macro step of the multibody ArmBody FMU against the decoupled FeaSegments.

The thesis's planar arm (six segments on a table, the FeaSegment defaults, no
gravity in the bending plane) stepped two ways in this one process, both through fmpy:
  arm body     one ArmBody FMU (planar, six segments)
  fea segments six FeaSegment FMUs, one substep of 1 ms each (their bending mode is integrated
               exactly)
each macro step setting the six piston positions (a slow sine) and reading the six bends, as a
master would. The arm's RK4 substep is its stability limit's: with the FeaSegment damping
d = 6e-3 N m s/rad the coupled arm's fastest mode (|lambda| = 9650 1/s, a damped tip motion)
needs 2.5e-4 s (four substeps); with the damping re-derived from silicone's loss tangent at the
coupled arm's first mode (d = 1.8e-3, fmus/ArmBody/README.md) 5e-4 s (two). Reported per row:
wall-clock microseconds per macro step (median of --repeat batches of --steps steps) and the
CPU time of this process per step (steadier on a shared host), for do_step alone and with the
inputs and outputs, and the ratios arm / segments. The target: the arm within 3x of the six
segments.

    python bench/arm_body_speed.py [--steps 2000] [--repeat 7]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Callable

from hil.fmu.build import build_fmu
from hil.fmu.slave import FmuSlave

N = 6
SEGMENT = {"L": 0.06, "mass": 0.03, "k": 0.025, "d": 6e-3, "G_a": 7.7e-7, "m_end": 0.0, "L_p": 0.0}
GAS = {"bore": 0.0254, "stroke": 0.05, "V_dead": 5e-6, "V_ch0": 8e-6, "C_a": 1e-10}
GAS |= {"vacuum_factor": 0.5, "p_collapse": 1e4, "x_seal": 0.025}
H = 1e-3


def piston(k: int, i: int) -> float:
    return 0.025 + 0.015 * math.sin(2 * math.pi * 0.5 * k * H + i)


def arm_parameters(damping: float, substep: float) -> dict[str, float]:
    params: dict[str, float] = {"n_segments": N, "planar": 1, "g_x": 0.0, "substep": substep}
    params |= GAS
    for i in range(1, N + 1):
        params |= {f"{name}_{i}": value for name, value in SEGMENT.items()}
        params[f"d_{i}"] = damping
        params[f"x_piston_x_{i}"] = 0.025
    return params


def measure(step: Callable[[int], None], steps: int, repeat: int) -> tuple[float, float]:
    """Median wall and CPU seconds per call of step(k) over `repeat` batches of `steps`."""
    k, wall, cpu = 0, [], []
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        for _ in range(steps):
            step(k)
            k += 1
        wall.append((time.perf_counter() - start) / steps)
        cpu.append((time.process_time() - start_cpu) / steps)
    return statistics.median(wall), statistics.median(cpu)


def time_arm(
    damping: float, substep: float, steps: int, repeat: int, io: bool
) -> tuple[float, float]:
    with FmuSlave(build_fmu("ArmBody"), "arm", arm_parameters(damping, substep)) as arm:
        inputs = [arm.value_reference(f"x_piston_x_{i}") for i in range(1, N + 1)]
        outputs = [arm.value_reference(f"theta_x_{i}") for i in range(1, N + 1)]

        def step(k: int) -> None:
            if io:
                arm.set_reals(inputs, [piston(k, i) for i in range(N)])
            arm.do_step(k * H, H)
            if io:
                arm.get_reals(outputs)

        return measure(step, steps, repeat)


def time_segments(steps: int, repeat: int, io: bool) -> tuple[float, float]:
    built = build_fmu("FeaSegment")
    segments = [FmuSlave(built, f"segment{i}") for i in range(1, N + 1)]
    try:
        x_piston = [s.value_reference("x_piston") for s in segments]
        theta = [s.value_reference("theta") for s in segments]

        def step(k: int) -> None:
            for i, segment in enumerate(segments):
                if io:
                    segment.set_reals([x_piston[i]], [piston(k, i)])
                segment.do_step(k * H, H)
                if io:
                    segment.get_reals([theta[i]])

        return measure(step, steps, repeat)
    finally:
        for segment in segments:
            segment.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()
    print(f"{'':44s}{'arm body':>10s}{'6 segments':>12s}{'ratio':>7s}{'cpu ratio':>11s}")
    for io in (False, True):
        wall_s, cpu_s = time_segments(args.steps, args.repeat, io)
        for damping, substep in ((6e-3, 2.5e-4), (1.8e-3, 5e-4)):
            wall_a, cpu_a = time_arm(damping, substep, args.steps, args.repeat, io)
            label = f"{'step+io' if io else 'step'}, d = {damping:g}, substep {substep:g} s"
            print(
                f"{label:44s}{wall_a * 1e6:8.1f}us{wall_s * 1e6:10.1f}us"
                f"{wall_a / wall_s:7.2f}{cpu_a / cpu_s:11.2f}"
            )


if __name__ == "__main__":
    main()
