"""The ArmBody reference result, fmus/ArmBody/ArmBody_ref.csv (as the Reference-FMUs keep one per
model): the default arm (four spatial segments, base horizontal) released straight and at rest,
drooping under gravity, 2 s at 1 ms sampled every 20 ms.

Regenerating the file is a deliberate act, reviewed like any golden file:

    python -m tests.arm_body_ref --regenerate

tests/test_arm_body.py compares the FMU against it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import fmus
from hil.fmu.build import build_fmu
from hil.fmu.slave import FmuSlave

PATH = fmus.source_root() / "ArmBody" / "ArmBody_ref.csv"
COLUMNS = [
    *(f"theta_x_{i}" for i in range(1, 5)),
    *(f"theta_dot_x_{i}" for i in range(1, 5)),
    "tip_x_4",
    "tip_z_4",
    "p_a_x_1",
    "p_b_x_1",
    "E_kinetic",
    "E_gravity",
    "E_elastic",
    "E_gas",
    "E_dissipated",
]
DURATION, EVERY = 2.0, 20  # [s], macro steps of 1 ms between samples


def simulate() -> np.ndarray:
    """Rows of (time, *COLUMNS) from the FMU built from the current sources."""
    rows = []
    with FmuSlave(build_fmu("ArmBody"), "arm") as arm:
        vrs = [arm.value_reference(name) for name in COLUMNS]
        rows.append([0.0, *arm.get_reals(vrs)])
        for k in range(int(round(DURATION / 1e-3))):
            arm.do_step(k * 1e-3, 1e-3)
            if (k + 1) % EVERY == 0:
                rows.append([(k + 1) * 1e-3, *arm.get_reals(vrs)])
    return np.array(rows)


def read(path: Path = PATH) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", skiprows=1)


def write(path: Path = PATH) -> None:
    np.savetxt(path, simulate(), delimiter=",", header=",".join(["time", *COLUMNS]), comments="")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--regenerate", action="store_true", help=f"rewrite {PATH}")
    args = parser.parse_args()
    if not args.regenerate:
        parser.error("nothing to do: --regenerate rewrites the reference result")
    write()
    print(f"wrote {PATH}")


if __name__ == "__main__":
    main()
