"""`hil estimate` and `hil tune`: estimation report of a recorded run; outer-loop design aid."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hil.errors import HilError


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli.parsers import example_parser

    estimate = example_parser(
        commands,
        "estimate",
        "run every estimator (raw, kf, ukf) over a recorded run's measurements and score it",
        "  hil estimate runs/default-1          table, estimation.json and estimation.png\n",
    )
    estimate.add_argument("run", type=Path, help="results folder of a run")
    estimate.add_argument("--no-plot", action="store_true", help="skip estimation.png")
    estimate.set_defaults(handler=_estimate)
    tune = example_parser(
        commands,
        "tune",
        "design the outer curvature PI for the scenario's estimator delay; margins, Bode plot",
        "  hil tune                        the default scenario\n"
        "  hil tune my.toml --out bode.png\n",
    )
    tune.add_argument(
        "scenario",
        nargs="?",
        type=Path,
        metavar="NAME|FILE",
        help="scenario NAME or FILE (default: built-in)",
    )
    tune.add_argument("--out", help="Bode plot PNG (default: tune-NAME.png)")
    tune.set_defaults(handler=_tune)


def _estimate(args: argparse.Namespace) -> int:
    from hil.estimation import check_estimable, estimation_report, read_run
    from hil.results import ESTIMATE_FILES, list_in_manifest, locked, write_file

    if args.run.is_file():
        raise HilError(
            f"{args.run}: is a file; give the results folder of a run ({args.run.parent})"
        )
    if not args.run.is_dir():
        raise HilError(f"{args.run}: no such results folder")
    check_estimable(args.run)  # robot kind, CSV log: refused before the folder is locked
    files = ESTIMATE_FILES if not args.no_plot else ("estimation.json",)
    writes = f"hil estimate writes {' and '.join(files)} there; copy the folder somewhere writable"
    with locked(args.run, writes):  # not while a run (or another estimate) writes there
        recorded = read_run(args.run)  # every input checked before anything is written
        # listed in the run's manifest first: a rerun with --overwrite replaces them too
        list_in_manifest(args.run, files)
        report = estimation_report(args.run, plot=not args.no_plot, recorded=recorded)
        text = json.dumps(report, indent=2, sort_keys=True) + "\n"
        write_file(args.run / "estimation.json", text)
    program = _program(args.run)
    used = (
        f"controller used {report['chosen']}"
        if program == "softhil"
        else f"the run's controller was {program}; softhil's would use {report['chosen']}"
    )
    print(f"{args.run}: estimation against the true curvature ({used})")
    print("  estimator   rms [1/m]   max [1/m]   gated   update [us]")
    for name in ("raw", "kf", "ukf"):
        r = report[name]
        print(
            f"  {name:9s} {r['rms']:10.4f} {r['max']:11.4f} {100 * r['gated']:6.2f} % "
            f"{1e6 * r['update_time']:11.0f}"
        )
    return 0


def _tune(args: argparse.Namespace) -> int:
    from hil.rig import robot_kind
    from hil.scenario import load_scenario, resolve_scenario
    from hil.seam import loop_design

    loops = loop_design()
    scenario = load_scenario(None if args.scenario is None else resolve_scenario(args.scenario))
    robot = robot_kind(scenario.robot.kind)
    if not hasattr(robot, "segment_models"):  # the outer curvature loop is the planar arm's
        raise HilError(
            f"{scenario.source}: hil tune applies to planar-arm scenarios, not robot kind "
            f"{scenario.robot.kind!r}"
        )
    c, T = scenario.controller, scenario.timing.control_period
    delay = loops.effective_delay(loops.estimator_delay(c.estimator, T, c.latency_compensation), T)
    out = _png_path(args.out) if args.out is not None else Path(f"tune-{scenario.name}.png")
    print(
        f"{scenario.name}: estimator {c.estimator} (latency compensation "
        f"{'on' if c.latency_compensation else 'off'}), effective delay {1e3 * delay:.1f} ms, "
        f"crossover cap {c.crossover:g} Hz"
    )
    for n, model in enumerate(robot.segment_models(scenario), start=1):  # type: ignore[attr-defined]
        design = loops.design_outer_loop(model, delay, max_crossover_hz=c.crossover)
        print(
            f"  segment {n}: Kp {design.gains.Kp:.5g} m/(1/m), Ki {design.gains.Ki:.5g} "
            f"m/(1/m s), crossover {design.crossover_hz:.2f} Hz, phase margin "
            f"{design.phase_margin_deg:.1f} deg, gain margin {_decibels(design.gain_margin)}"
        )
        if n == 1:
            try:
                loops.write_bode_png(model, design, out)
            except OSError as exc:
                raise HilError(f"--out {out}: cannot write: {exc.strerror or exc}") from None
    print(f"  Bode plot of segment 1: {out}")
    return 0


def _png_path(given: str) -> Path:
    """The Bode plot's file for --out: a PNG file (".png" added to a name without a suffix) in
    an existing folder; HilError naming the path otherwise."""
    if not given:
        raise HilError("--out: an empty file name; name the PNG file")
    out = Path(given)
    if given.endswith("/"):
        raise HilError(f"--out {out}: names a folder (it ends in /); name the PNG file")
    if out.is_dir():
        raise HilError(f"--out {out}: is a folder; name the PNG file (e.g. {out / 'bode.png'})")
    if not out.suffix:
        out = out.with_name(out.name + ".png")
    if out.suffix.lower() != ".png":
        raise HilError(f"--out {out}: the Bode plot is a PNG; name a .png file")
    folder = out.parent
    if not folder.is_dir():
        reason = "is not a folder" if folder.exists() else "no such folder"
        raise HilError(f"--out {out}: {folder}: {reason}")
    return out


def _decibels(ratio: float) -> str:
    import math

    return "infinite" if not math.isfinite(ratio) else f"{20.0 * math.log10(ratio):.1f} dB"


def _program(run: Path) -> str:
    """Who controlled the run, as summary.json says: "softhil" (also when it does not say),
    "an external controller", or "your program"."""
    try:
        program = json.loads((run / "summary.json").read_text()).get("controller_program")
    except (OSError, ValueError, AttributeError):
        return "softhil"
    if program in (None, "softhil"):
        return "softhil"
    return "an external controller" if program == "external" else "your program"
