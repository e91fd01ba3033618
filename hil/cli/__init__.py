"""The `hil` command: one module per subcommand, listed explicitly in `SUBCOMMANDS`.

Every error a user can cause reaches the terminal as one line `hil: error: ...` and a non-zero exit
code; `hil --debug ...` shows the traceback instead. Exit codes (the controller program uses the
same): 0 success, 1 an error (the line says which), 2 wrong usage, 130 interrupted (SIGINT), 143
terminated (SIGTERM).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Callable, Sequence

from hil.cli import batch as batch_command
from hil.cli import bus as bus_command
from hil.cli import controller as controller_command
from hil.cli import envelope as envelope_command
from hil.cli import estimate as estimate_command
from hil.cli import fmu as fmu_command
from hil.cli import replay as replay_command
from hil.cli import run as run_command
from hil.cli import scenarios as scenarios_command
from hil.cli import signals_csv as csv_command
from hil.cli.parsers import HelpFormatter
from hil.environment import check as check_environment
from hil.errors import HilError, Terminated
from rigbus.protocol import FrameError

SUBCOMMANDS = (
    run_command,
    scenarios_command,
    batch_command,
    replay_command,
    estimate_command,
    envelope_command,
    csv_command,
    controller_command,
    bus_command,
    fmu_command,
)

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 2, 130, 143

EXAMPLES = """examples:
  hil run                         run the default scenario, results in ./runs/<name>-<seed>/
  hil run my.toml --inprocess     controller in this process, virtual bus
  hil scenarios                   the built-in scenarios (hil run NAME runs one)
  hil batch --trials 20           20 seeds of the default scenario in parallel
  hil sweep --set controller.crossover=0.5,1,2   a parameter grid
  hil bus load                    bus load of the default scenario
  hil csv runs/default-1          signals.csv from a killed run's blocks
  hil envelope spatial-point      the spatial arm's statically reachable envelope
  hil fmu build                   build every FMU into the per-user cache
  hil fmu check DriveCylinder     validate an FMU with fmpy and simulate it briefly

exit codes: 0 success, 1 error, 2 wrong usage, 130 interrupted, 143 terminated
"""


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("softhil")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hil",
        description="softhil: hardware-in-the-loop style co-simulation of soft fluidic robots.",
        epilog=EXAMPLES,
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in SUBCOMMANDS:
        module.add_parser(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if "--debug" in extra:  # after the command too (`hil run x --debug`), as users type it
        args.debug = True
        extra = [word for word in extra if word != "--debug"]
    if extra:  # in the usage of the command they were given to, not hil's
        (getattr(args, "command_parser", None) or parser).error(
            f"unrecognized arguments: {' '.join(extra)}"
        )
    handler: Callable[[argparse.Namespace], int] | None = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return EXIT_USAGE
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if main_thread else None
    try:
        check_environment()
        return handler(args)
    except Terminated:
        print("hil: terminated", file=sys.stderr)
        return EXIT_TERMINATED
    except (HilError, FrameError) as error:  # FrameError: the DBC itself is unreadable
        if args.debug:
            raise
        print(f"hil: error: {error}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("hil: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # `hil fmu list | head`
        sys.stderr.close()
        return 0
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


def _terminate(signum: int, frame: object) -> None:
    """SIGTERM (CI runners, containers, `kill`): unwind like Ctrl-C, once; a second TERM during
    the cleanup is ignored (KILL still ends the process)."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise Terminated
