"""`hil replay`: replay a recorded run's CAN log against a controller and compare its frames."""

from __future__ import annotations

import argparse
import contextlib
import json
from pathlib import Path

from hil.errors import HilError


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli.parsers import example_parser

    parser = example_parser(
        commands,
        "replay",
        "replay a recorded CAN log to the controller and compare what it sends, signal by signal",
        "  hil replay runs/default-1/can.log                 the run's own controller.json\n"
        "  hil replay runs/default-1/can.blf --process       controller as a separate program\n"
        "  hil replay runs/default-1/can.log --scenario changed.toml   a changed controller\n"
        "  hil replay can.log --tolerance 1e-3 --tolerance-for kappa_est=0.01\n"
        "  hil replay runs/mine/can.log --controller 'python my_ctrl.py --config {config} "
        "--bus {bus}'\n"
        "                                                    your controller program\n",
    )
    parser.add_argument("log", type=Path, help="CAN log of a run (any format python-can reads)")
    parser.add_argument(
        "--scenario",
        type=Path,
        help="scenario NAME or FILE whose controller to replay (default: controller.json beside "
        "the log)",
    )
    parser.add_argument(
        "--tolerance",
        type=float,
        default=0.0,
        help="allowed absolute difference of every signal, in its unit",
    )
    parser.add_argument(
        "--tolerance-for",
        action="append",
        default=[],
        metavar="SIGNAL=VALUE",
        help="a signal's own tolerance (SIGNAL or MESSAGE.SIGNAL); repeatable",
    )
    parser.add_argument(
        "--process", action="store_true", help="run the controller as a separate program"
    )
    parser.add_argument(
        "--controller",
        default="softhil",
        metavar="softhil|COMMAND",
        help="the controller program, as hil run --controller takes it: softhil's own, or your "
        "command line with {config} {bus} ... (a separate program: implies --process)",
    )
    parser.add_argument(
        "--wait",
        type=float,
        default=None,
        metavar="SECONDS",
        help="how long the replay waits for the controller's first SYNC (default: 60); after "
        "that, 10 s for each further frame",
    )
    parser.add_argument(
        "--json",
        type=Path,
        help="write the comparison's summary as JSON (not over a CAN log or a run's files)",
    )
    parser.set_defaults(handler=_replay)


def _replay(args: argparse.Namespace) -> int:
    from hil.replay import replay
    from hil.results import write_file
    from hil.rig import robot_kind
    from hil.scenario import load_scenario, resolve_scenario

    tolerances: dict[str, float] = {}
    for item in args.tolerance_for:
        name, sep, value = item.partition("=")
        try:
            tolerances[name] = float(value)
        except ValueError:
            raise HilError(f"--tolerance-for {item!r}: expected SIGNAL=NUMBER") from None
        if not sep or not name or not tolerances[name] >= 0:  # nan too
            raise HilError(f"--tolerance-for {item!r}: expected SIGNAL=NUMBER >= 0")
    if not args.tolerance >= 0:
        raise HilError(f"--tolerance must not be negative, got {args.tolerance}")
    json_out = _json_path(args.json, Path(args.log)) if args.json else None
    config = None
    try:
        if args.scenario is not None:
            scenario = load_scenario(resolve_scenario(args.scenario))
            config = robot_kind(scenario.robot.kind).controller_config(scenario)
        result = replay(
            args.log,
            config,
            process=args.process,
            controller=args.controller,
            tolerance=args.tolerance,
            tolerances=tolerances,
            **({} if args.wait is None else {"wait": args.wait}),
        )
    except (HilError, KeyboardInterrupt) as exc:
        if json_out:  # an earlier replay's report is not left there, read as this one's
            error = str(exc) if isinstance(exc, HilError) else "interrupted (SIGINT)"
            with contextlib.suppress(HilError):
                write_file(
                    json_out, json.dumps({"status": "error", "error": error}, indent=2) + "\n"
                )
        raise
    print(
        f"{args.log}: {result.cycles} cycles, {result.frames_compared} controller frames "
        f"compared, {len(result.divergences)} divergence(s)"
    )
    if not result.ok:
        print(f"  first divergence: {result.divergences[0]}")
        for signal, count in sorted(result.by_signal.items()):
            print(f"  {signal}: {count} cycle(s)")
    if json_out:  # after the report: a failing write loses no result
        report = {"status": "passed" if result.ok else "diverged", **result.summary()}
        write_file(json_out, json.dumps(report, indent=2) + "\n")
    return 0 if result.ok else 1


def _json_path(out: Path, log: Path) -> Path:
    """--json's file, checked before the replay runs: not a folder, in an existing folder, and
    not a file that holds a recording: the log being replayed, another CAN log, a file of a
    run's results, or a run folder's lock or manifest (an earlier replay's JSON may be
    replaced)."""
    from hil.bustools.logs import SUFFIXES as LOG_SUFFIXES
    from hil.results import ESTIMATE_FILES, LOCK, MANIFEST, RESULT_FILES, manifest_names

    if out.name.casefold() in (LOCK.casefold(), MANIFEST.casefold()):  # there or not
        raise HilError(f"--json {out}: is softhil's own {out.name} of a run; name another file")
    if out.is_file():
        with contextlib.suppress(OSError):
            if out.samefile(log):
                raise HilError(f"--json {out}: is the log being replayed; name another file")
        listed = out.name in manifest_names(out.parent)
        if out.suffix.lower() in LOG_SUFFIXES:
            raise HilError(f"--json {out}: is a CAN log; name another file")
        if listed or out.name.casefold() in {n.casefold() for n in RESULT_FILES + ESTIMATE_FILES}:
            raise HilError(f"--json {out}: is a file of the run in {out.parent}; name another file")
    if out.is_dir():
        raise HilError(
            f"--json {out}: is a folder; name the JSON file (e.g. {out / 'replay.json'})"
        )
    if not out.parent.is_dir():
        reason = "is not a folder" if out.parent.exists() else "no such folder"
        raise HilError(f"--json {out}: {out.parent}: {reason}")
    return out
