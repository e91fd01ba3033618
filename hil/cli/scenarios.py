"""`hil scenarios`: the built-in scenarios, one line each (`hil run NAME` runs one); with
`--keys`, the reference of every scenario key (hil.scenario_reference)."""

from __future__ import annotations

import argparse

from hil.scenario import builtin_scenarios


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli.parsers import example_parser

    parser = example_parser(
        commands,
        "scenarios",
        "list the built-in scenarios (hil run NAME, hil batch NAME, hil sweep NAME)",
        "  hil scenarios\n  hil run default\n"
        "  hil scenarios --keys          every key a scenario can hold\n",
    )
    parser.add_argument("--paths", action="store_true", help="also show each scenario's file")
    parser.add_argument(
        "--keys",
        action="store_true",
        help="print the reference of every scenario key (Markdown: docs/scenario-keys.md)",
    )
    parser.set_defaults(handler=_scenarios)


def _scenarios(args: argparse.Namespace) -> int:
    if args.keys:
        from hil.scenario_reference import reference

        print(reference(), end="")
        return 0
    scenarios = builtin_scenarios()
    width = max((len(name) for name in scenarios), default=0)
    for scenario in scenarios.values():
        line = f"{scenario.name:<{width}}  {scenario.description}".rstrip()
        print(f"{line}  ({scenario.path})" if args.paths else line)
    return 0
