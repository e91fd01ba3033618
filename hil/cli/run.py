"""`hil run`: run a scenario (placeholder until the closed loop lands)."""

from __future__ import annotations

import argparse


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli import example_parser

    parser = example_parser(commands, "run", "run a scenario", "  hil run\n")
    parser.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    print("hil run: the closed loop over CAN is not built yet")
    return 0
