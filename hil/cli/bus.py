"""`hil bus`: bus tools. `serve` runs the loopback inter-process CAN hub in the foreground."""

from __future__ import annotations

import argparse

from hil.bus import loopback
from hil.errors import HilError


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli import example_parser

    parser = example_parser(
        commands,
        "bus",
        "CAN bus tools",
        "  hil bus serve                    loopback hub on 127.0.0.1:29536\n"
        "  hil bus load                     bus load of the default scenario\n",
    )
    sub = parser.add_subparsers(dest="bus_command", metavar="ACTION", required=True)
    serve = example_parser(
        sub,
        "serve",
        "serve the loopback CAN hub (socketcand protocol) until Ctrl-C",
        "  hil bus serve --port 29536\n"
        "  python -c \"import can; can.Bus(interface='socketcand', channel='softhil', "
        "host='127.0.0.1', port=29536)\"\n",
    )
    serve.add_argument("--host", default="127.0.0.1", help="address to bind (loopback only)")
    serve.add_argument("--port", type=int, default=loopback.DEFAULT_PORT, help="TCP port")
    serve.add_argument(
        "--allow-remote",
        action="store_true",
        help="allow a non-loopback --host (other machines can join the bus)",
    )
    serve.set_defaults(handler=_serve)
    load = example_parser(
        sub,
        "load",
        "bus load a scenario implies, computed from the DBC at its bitrate",
        "  hil bus load\n  hil bus load my.toml --bitrate 250000\n",
    )
    load.add_argument("scenario", nargs="?", help="scenario TOML (default: built-in)")
    load.add_argument("--bitrate", type=int, help="override the scenario's bitrate [bit/s]")
    load.set_defaults(handler=_load)


def _serve(args: argparse.Namespace) -> int:
    extra = ["--allow-remote"] if args.allow_remote else []
    return loopback.main(["--host", args.host, "--port", str(args.port), *extra])


def _load(args: argparse.Namespace) -> int:
    from dataclasses import replace
    from pathlib import Path

    from controllers.protocol import Protocol
    from hil.scenario import load_scenario
    from hil.summary import BUS_LOAD_WARNING, bus_load_of

    scenario = load_scenario(Path(args.scenario) if args.scenario else None)
    if args.bitrate is not None and args.bitrate <= 0:
        raise HilError(f"--bitrate must be positive, got {args.bitrate}")
    if args.bitrate:
        scenario = replace(scenario, bus=replace(scenario.bus, bitrate=args.bitrate))
    load = bus_load_of(scenario, Protocol())
    print(
        f"{scenario.name}: bus load {100 * load:.1f} % at {scenario.bus.bitrate} bit/s "
        "(worst-case bit stuffing)"
    )
    if load > BUS_LOAD_WARNING:
        print(
            f"warning: above {100 * BUS_LOAD_WARNING:.0f} %: frames will be delayed on a real bus"
        )
    return 0
