"""The `hil` command: one module per subcommand, listed explicitly in `SUBCOMMANDS`.

Every error a user can cause reaches the terminal as one line `hil: error: ...` and a non-zero exit
code; `hil --debug ...` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from hil.cli import bus as bus_command
from hil.cli import controller as controller_command
from hil.cli import fmu as fmu_command
from hil.cli import run as run_command
from hil.errors import HilError

SUBCOMMANDS = (run_command, controller_command, bus_command, fmu_command)

EXAMPLES = """examples:
  hil run                         run the default scenario, results in ./runs/<name>-<seed>/
  hil run my.toml --inprocess     controller in this process, virtual bus
  hil bus load                    bus load of the default scenario
  hil fmu build                   build every FMU into the per-user cache
  hil fmu check DriveCylinder     validate an FMU with fmpy and simulate it briefly
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hil",
        description="softhil: hardware-in-the-loop style co-simulation of soft fluidic robots.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in SUBCOMMANDS:
        module.add_parser(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Callable[[argparse.Namespace], int] | None = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return 2
    try:
        return handler(args)
    except HilError as error:
        if args.debug:
            raise
        print(f"hil: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("hil: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `hil fmu list | head`
        sys.stderr.close()
        return 0


def example_parser(
    commands: argparse._SubParsersAction, name: str, help_text: str, examples: str
) -> argparse.ArgumentParser:
    """A subcommand parser whose help ends with examples."""
    return commands.add_parser(
        name,
        help=help_text,
        description=help_text,
        epilog="examples:\n" + examples,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
