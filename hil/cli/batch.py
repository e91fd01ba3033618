"""`hil batch` and `hil sweep`: seeded trials and parameter grids, locally or on Dask."""

from __future__ import annotations

import argparse
import shlex
import sys
import textwrap
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hil.batch.planning import Override, Plan, count, make_plan, parse_set
from hil.batch.runner import Execution, run_plan
from hil.errors import HilError
from hil.scenario import resolve_scenario

WARNED_SHOWN = 5  # trials with warnings named on the terminal; batch.json lists them all
BATCH_EXAMPLES = (
    "  hil batch                                   10 seeds of the default scenario\n"
    "  hil batch planar-point-to-point --trials 50 --out runs/p2p\n"
    "  hil batch my.toml --trials 20 --seed 100    seeds 100..119\n"
    "  hil batch --scheduler tcp://10.0.0.5:8786   the same trials on a Dask cluster\n"
)
SWEEP_EXAMPLES = (
    "  hil sweep --set controller.crossover=0.5,1.0,2.0\n"
    "  hil sweep --set controller.crossover=0.5,1.0 --set camera.noise=0.0005,0.001 --trials 5\n"
    "  hil sweep --set controller.estimator=raw,kf,ukf   (bare words are strings)\n"
    "  hil sweep --set cylinder.bore=0.02,0.0254        ([robot] keys need no 'robot.')\n"
)
COMMON = (
    "Trials run in-process on --workers local processes, or on the workers of a Dask scheduler "
    "(`dask scheduler`; `dask worker ADDRESS --nthreads 1` on every machine, with softhil "
    "installed and DIR on a shared filesystem); the results are identical. DIR gets batch.json "
    "(per-trial metrics and warnings, mean, std, min, max, success rate), timing.json (wall "
    "times), batch.png and one run folder per trial."
)


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli.parsers import example_parser

    batch = example_parser(
        commands, "batch", "run a scenario with N seeds in parallel and aggregate", BATCH_EXAMPLES
    )
    batch.description = textwrap.fill(f"{batch.description}. {COMMON}", 79)
    _common(batch, trials=10)
    batch.set_defaults(handler=_batch)

    sweep = example_parser(
        commands,
        "sweep",
        "run a scenario over a grid of parameter values (each with --trials seeds)",
        SWEEP_EXAMPLES,
    )
    sweep.description = textwrap.fill(f"{sweep.description}. {COMMON}", 79)
    sweep.add_argument(
        "--set",
        dest="sets",
        action="append",
        required=True,
        metavar="SECTION.KEY=V1,V2,...",
        help="a swept key (dotted TOML path; one whose first part is not a top-level scenario "
        "key is a [robot] key: valve.open_time is robot.valve.open_time) and "
        "its values as TOML (numbers, true/false, quoted strings; a bare word is a string); "
        "repeat for a grid, the cartesian product of all",
    )
    _common(sweep, trials=1)
    sweep.set_defaults(handler=_sweep)


def _common(parser: argparse.ArgumentParser, trials: int) -> None:
    parser.add_argument(
        "scenario",
        nargs="?",
        default="default",
        metavar="NAME|FILE",
        help="a scenario TOML file, or the name of a built-in scenario (`hil scenarios`) "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--trials",
        type=int,
        default=trials,
        metavar="N",
        help="seeds per run (per grid point in a sweep)",
    )
    parser.add_argument(
        "--seed",
        type=int,
        metavar="S",
        help="first seed; trial t runs seed S + t (default: the scenario's seed)",
    )
    parser.add_argument(
        "--out",
        metavar="DIR",
        help="results folder, new or empty (default: runs/NAME-batch-SEED or runs/NAME-sweep-SEED)",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="reuse a results folder: replace the files and trial folders an earlier batch "
        "wrote there (listed in its .softhil-manifest), never other files",
    )
    parser.add_argument(
        "--workers",
        type=int,
        metavar="W",
        help="local worker processes (default: the number of cores)",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run on this dask.distributed scheduler (tcp://HOST:8786) instead of locally",
    )
    parser.add_argument(
        "--controller",
        default="softhil",
        metavar="softhil|COMMAND",
        help="the controller program, as hil run --controller takes it: softhil's own (in each "
        "trial's process), or your command line with {config} {bus} ... (a process beside "
        "each trial; on a dask cluster, where every worker finds it)",
    )
    parser.add_argument(
        "--no-reports",
        action="store_true",
        help="skip each trial's plots and reports, as hil run --no-reports does (batch.json and "
        "every trial's CAN log, signals and summary are the same)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _batch(args: argparse.Namespace) -> int:
    return _execute(args, "batch", [])


def _sweep(args: argparse.Namespace) -> int:
    return _execute(args, "sweep", [parse_set(option) for option in args.sets])


def _execute(args: argparse.Namespace, kind: str, overrides: list[Override]) -> int:
    if args.out is not None and not args.out.strip():
        raise HilError("--out: an empty folder name; name the results folder")
    if args.workers is not None and args.scheduler:
        raise HilError("--workers: local workers only; a Dask cluster has its own")
    if args.workers is not None and args.workers < 1:
        raise HilError(f"--workers: must be at least 1, got {args.workers}")
    source = resolve_scenario(args.scenario)
    plan = make_plan(
        source,
        kind=kind,
        command=_command(args, kind),
        out=Path(args.out) if args.out else None,
        trials=args.trials,
        seed=args.seed,
        overrides=overrides,
        controller=args.controller,
        reports=not args.no_reports,
    )
    content = run_plan(
        plan,
        Execution(workers=args.workers, scheduler=args.scheduler, progress=not args.no_progress),
        overwrite=args.overwrite,
    )
    _print(plan, content)
    failed = content["failed_trials"]
    if failed:
        first = failed[0]
        raise HilError(
            f"{len(failed)} of {len(content['trials'])} trials failed, the first: trial "
            f"{first['index']} (seed {first['seed']}, {plan.out / first['folder']}): "
            f"{first['error']}; all results in {plan.out / 'batch.json'}"
        )
    return 0


def _command(args: argparse.Namespace, kind: str) -> str:
    """The options that decide the results: batch.json records them, not --out, where the
    trials ran or whether they drew their reports (so local and Dask runs, with --no-reports
    or without, write the same file)."""
    words = ["hil", kind, args.scenario, "--trials", str(args.trials)]
    if args.seed is not None:
        words += ["--seed", str(args.seed)]
    for option in getattr(args, "sets", None) or []:
        words += ["--set", option]
    if args.controller != "softhil":
        words += ["--controller", args.controller]
    return shlex.join(words)


def _print(plan: Plan, content: Mapping[str, Any]) -> None:
    trials = content["trials"]
    print(
        f"{plan.scenario}: {plan.kind} of {count(len(trials), 'trial')}, {content['completed']} "
        "completed"
        + (f", success rate {content['success_rate']:.0%}" if "success_rate" in content else "")
    )
    for name, stats in content["aggregate"].items():
        print(f"  {name:<24} {_stats(stats)}")
    for point in content.get("points", []):
        label = " ".join(f"{k}={v}" for k, v in point["overrides"].items())
        print(f"  [{label}]")
        for name, stats in point["aggregate"].items():
            print(f"    {name:<22} {_stats(stats)}")
    for trial in content["failed_trials"]:
        print(
            f"  failed: trial {trial['index']} (seed {trial['seed']}): {trial['error']}",
            file=sys.stderr,
        )
    warned = content["warned_trials"]
    for trial in warned[:WARNED_SHOWN]:
        more = len(trial["warnings"]) - 1
        print(
            f"  warning: trial {trial['index']} (seed {trial['seed']}): {trial['warnings'][0]}"
            + (f" (and {more} more)" if more else ""),
            file=sys.stderr,
        )
    if len(warned) > WARNED_SHOWN:
        print(
            f"  warning: {len(warned) - WARNED_SHOWN} more trials with warnings: "
            "warned_trials in batch.json",
            file=sys.stderr,
        )
    print(f"  results in {plan.out}/ (batch.json, batch.png, timing.json, trial-*/)")


def _stats(stats: Mapping[str, Any]) -> str:
    std = "n/a" if stats["std"] is None else f"{stats['std']:.4g}"
    return (
        f"mean {stats['mean']:.4g}  std {std}  min {stats['min']:.4g}  max {stats['max']:.4g}  "
        f"n {stats['n']}"
    )
