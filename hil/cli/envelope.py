"""`hil envelope`: a robot's statically reachable envelope (every tip position it can rest at
under gravity), computed from its static model, drawn and exported (.npz with the bends and
pistons of every rest, .csv with the tips) for tasks and studies that need it.

A robot kind has an envelope when its plant side provides `envelope(scenario, samples)` and
`draw_envelope(scenario, envelope, path)` (the spatial arm does).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from hil.errors import HilError


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli.parsers import example_parser

    parser = example_parser(
        commands,
        "envelope",
        "the robot's statically reachable envelope under gravity: drawn and exported",
        "  hil envelope spatial-point            envelope.png, .npz and .csv in "
        "envelope-spatial-point/\n"
        "  hil envelope spatial-point --samples 20000 --out env\n",
    )
    parser.add_argument("scenario", type=Path, metavar="NAME|FILE", help="scenario NAME or FILE")
    parser.add_argument("--out", type=Path, help="folder (default: envelope-NAME)")
    parser.add_argument(
        "--samples",
        type=int,
        help="static rests sampled (default: the scenario's robot.envelope_samples)",
    )
    parser.set_defaults(handler=_envelope)


def _envelope(args: argparse.Namespace) -> int:
    from hil.results import write_file
    from hil.rig import robot_kind
    from hil.scenario import load_scenario, resolve_scenario

    scenario = load_scenario(resolve_scenario(args.scenario))
    robot: Any = robot_kind(scenario.robot.kind)  # an optional part of a robot kind
    if not hasattr(robot, "envelope"):
        raise HilError(
            f"{scenario.source}: robot kind {scenario.robot.kind!r} has no statically "
            "reachable envelope (hil envelope applies to the spatial arm)"
        )
    if args.samples is not None and args.samples < 50:
        raise HilError(f"--samples: at least 50, got {args.samples}")
    out: Path = args.out or Path(f"envelope-{scenario.name}")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HilError(f"{out}: cannot make the folder: {exc.strerror}") from None
    envelope = robot.envelope(scenario, args.samples)
    report = robot.envelope_report(scenario, envelope)
    for name, data in robot.envelope_files(envelope).items():
        write_file(out / name, data)
    robot.draw_envelope(scenario, envelope, out / "envelope.png")
    print(f"{scenario.name}: {report}")
    print(f"  written to {out}/ (envelope.png, envelope.npz, envelope.csv)")
    return 0
