"""`hil fmu build|list|check`: the FMU toolchain from the command line."""

from __future__ import annotations

import argparse
import contextlib
import io
import math
from pathlib import Path

import fmus
from hil.errors import HilError
from hil.fmu.build import build_fmu


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli.parsers import example_parser

    parser = example_parser(
        commands,
        "fmu",
        "build, list and check the softhil FMUs",
        "  hil fmu build                 build all models (cached until a source changes)\n"
        "  hil fmu build FeaSegment -f   force a rebuild of one model\n"
        "  hil fmu list                  models, variables, units and defaults\n"
        "  hil fmu check DriveCylinder   fmpy validation plus a short simulation\n",
    )
    sub = parser.add_subparsers(dest="fmu_command", metavar="ACTION", required=True)
    build = example_parser(
        sub, "build", "build FMUs from their C sources", "  hil fmu build DriveCylinder\n"
    )
    build.add_argument("names", nargs="*", metavar="NAME", help="models to build (default: all)")
    build.add_argument("-f", "--force", action="store_true", help="rebuild even if cached")
    build.set_defaults(handler=_build)
    listing = example_parser(
        sub, "list", "list the models and their variables", "  hil fmu list FeaSegment\n"
    )
    listing.add_argument("names", nargs="*", metavar="NAME", help="models to list (default: all)")
    listing.set_defaults(handler=_list)
    check = example_parser(
        sub,
        "check",
        "validate an FMU with fmpy and simulate it for a short time",
        "  hil fmu check FeaSegment\n  hil fmu check path/to/Other.fmu\n",
    )
    check.add_argument("name", metavar="NAME", help="a softhil model name or a path to an .fmu")
    check.add_argument(
        "--stop-time",
        type=float,
        default=0.5,
        help=f"simulated time [s], at most {MAX_CHECK_STOP_TIME:g}",
    )
    check.add_argument(
        "--step",
        type=float,
        help="communication step [s] (default: the model's step, doubled until at most 1000 "
        f"steps); at most {MAX_CHECK_STEPS} steps",
    )
    check.set_defaults(handler=_check)


MAX_CHECK_STOP_TIME = 100.0
"""Longest `hil fmu check` simulation [s]: the FMUs take RK4 substeps of 20-100 us inside each
step, so simulated time, not the number of steps, sets the cost (about 1 s of CPU per 100 s for
DriveCylinder); a check is a smoke test, `hil run` is for long simulations."""

MAX_CHECK_STEPS = 100_000
"""Most communication steps of `hil fmu check` (each is a Python round trip in fmpy)."""


def _check_limits(stop_time: float, step: float | None) -> None:
    """One-line errors for a stop time or step that would make the check hang or fail."""
    if not 0 < stop_time <= MAX_CHECK_STOP_TIME:
        raise HilError(
            f"--stop-time must be in (0, {MAX_CHECK_STOP_TIME:g}] s for a check, got {stop_time:g}"
            " (use hil run for long simulations)"
        )
    if step is None:
        return
    if not 0 < step <= stop_time:
        raise HilError(f"--step must be in (0, --stop-time {stop_time:g}] s, got {step:g}")
    if stop_time / step > MAX_CHECK_STEPS:
        raise HilError(
            f"--step {step:g} s would take {stop_time / step:.3g} steps to reach --stop-time "
            f"{stop_time:g} s; at most {MAX_CHECK_STEPS} are allowed (use a larger --step)"
        )


def _names(requested: list[str]) -> list[str]:
    return requested or fmus.model_names()


def _build(args: argparse.Namespace) -> int:
    for name in _names(args.names):
        built = build_fmu(name, force=args.force)
        print(f"{name}: {built.path}")
    return 0


def _format_value(value: float | None, vtype: str) -> str:
    if value is None:
        return "-"
    if vtype == "Boolean":
        return "true" if value else "false"
    return f"{value:g}"


def _list(args: argparse.Namespace) -> int:
    from hil.fmu.build import model_folder
    from hil.fmu.spec import load_spec

    for name in _names(args.names):
        spec = load_spec(model_folder(name))
        print(f"{spec.name}: {spec.description}")
        rows = [("name", "causality", "type", "unit", "start", "description")]
        rows += [
            (
                v.name,
                v.causality,
                v.type,
                v.unit or "",
                _format_value(v.start, v.type),
                v.description,
            )
            for v in spec.variables
        ]
        widths = [max(len(row[i]) for row in rows) for i in range(5)]
        for row in rows:
            print(
                "  "
                + "  ".join(cell.ljust(w) for cell, w in zip(row[:5], widths, strict=True))
                + "  "
                + row[5]
            )
        print()
    return 0


def _check(args: argparse.Namespace) -> int:
    from fmpy import read_model_description, simulate_fmu
    from fmpy.validation import validate_fmu

    _check_limits(args.stop_time, args.step)
    path = Path(args.name)
    if path.suffix == ".fmu":
        if not path.is_file():
            raise HilError(f"{path}: no such FMU file")
        fmu_path = path
    else:
        fmu_path = build_fmu(args.name).path
    try:
        problems = validate_fmu(str(fmu_path))
    except Exception as exc:  # fmpy lets zipfile and XML errors through
        raise HilError(f"{fmu_path}: not a readable FMU: {exc}") from exc
    if problems:
        for problem in problems:
            print(f"{fmu_path}: {problem}")
        raise HilError(f"{fmu_path}: fmpy validation found {len(problems)} problem(s)")
    description = read_model_description(str(fmu_path))
    outputs = [v.name for v in description.modelVariables if v.causality == "output"]
    stepped = _input_steps(description, args.stop_time)
    chatter = io.StringIO()
    try:
        with contextlib.redirect_stdout(chatter):  # fmpy prints a line per unset input
            result = simulate_fmu(
                str(fmu_path),
                stop_time=args.stop_time,
                output=outputs,
                fmi_type="CoSimulation",
                input=stepped,
                output_interval=args.step,
            )
    except Exception as exc:  # fmpy raises plain exceptions for FMI errors
        raise HilError(f"{fmu_path}: simulation in fmpy failed: {exc}") from exc
    bad = [name for name in outputs if not all(math.isfinite(float(x)) for x in result[name])]
    if bad:
        raise HilError(f"{fmu_path}: non-finite outputs in fmpy simulation: {', '.join(bad)}")
    print(f"{description.modelName}: fmpy validation passed")
    moved = (
        ""
        if stepped is None
        else (
            f", Real inputs stepped by +20 % at {args.stop_time / 2:g} s ("
            + ", ".join(n for n in stepped.dtype.names if n != "time")
            + ")"
        )
    )
    print(
        f"{description.modelName}: simulated {args.stop_time:g} s in fmpy{moved}, "
        f"{len(result)} samples, outputs finite"
    )
    units = {v.name: _unit_of(v) for v in description.modelVariables}
    for name in outputs:
        unit = units.get(name, "")
        print(f"  {name} = {float(result[name][-1]):.6g}{' ' + unit if unit else ''}")
    return 0


def _unit_of(variable: object) -> str:
    """A variable's unit as its modelDescription declares it ('' for dimensionless)."""
    unit = getattr(variable, "unit", None) or getattr(
        getattr(variable, "declaredType", None), "unit", None
    )
    return "" if unit in (None, "1") else str(unit)


def _input_steps(description, stop_time: float):  # noqa: ANN001, ANN202 - fmpy types
    """An fmpy input table stepping every Real input with a non-zero start by +20 % halfway,
    so that the check exercises the dynamics instead of a model at rest (None: no such input)."""
    import numpy as np

    inputs = [
        v
        for v in description.modelVariables
        if v.causality == "input"
        and v.type == "Real"
        and v.start not in (None, "0", "0.0")
        and float(v.start) != 0.0
    ]
    if not inputs:
        return None
    dtype = [("time", np.float64)] + [(v.name, np.float64) for v in inputs]
    start = tuple(float(v.start) for v in inputs)
    stepped = tuple(1.2 * value for value in start)
    half = stop_time / 2
    return np.array([(0.0, *start), (half, *start), (half, *stepped)], dtype=dtype)
