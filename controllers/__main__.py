"""`python -m controllers`: the controller node as its own program (also `hil controller`).

It reads its configuration (written by `hil run` into the run folder), opens the bus and runs the
experiment as the SYNC producer. Errors print one line and exit 1.
"""

from __future__ import annotations

import argparse
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from controllers.canbus import BusOpenError, BusSpec, open_bus
from controllers.node import (
    ControllerConfig,
    ControllerError,
    ControllerNode,
    LockstepClock,
    RealtimeClock,
    write_report,
)
from controllers.protocol import FrameError

EXAMPLES = """examples:
  python -m controllers --config runs/default-1/controller.json --bus loopback:29536
  hil controller --config controller.json --bus loopback:127.0.0.1:29536 --realtime
"""


def build_parser(prog: str = "python -m controllers") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description="softhil controller node: SYNC producer, curvature control over CAN.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_arguments(parser)
    return parser


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, type=Path, help="controller.json of a run")
    parser.add_argument("--bus", default="loopback", help="bus spec (default: loopback)")
    parser.add_argument("--realtime", action="store_true", help="pace SYNC on the wall clock")
    parser.add_argument("--report", type=Path, help="write the controller's report (JSON)")


def run(args: argparse.Namespace) -> int:
    try:
        config = ControllerConfig.from_json(args.config.read_text())
    except KeyError as exc:
        print(f"controller: error: {args.config}: missing key {exc}", file=sys.stderr)
        return 1
    except (OSError, ValueError, TypeError) as exc:
        print(f"controller: error: {args.config}: {exc}", file=sys.stderr)
        return 1
    try:
        bus = open_bus(BusSpec.parse(args.bus))
    except (BusOpenError, ValueError) as exc:
        print(f"controller: error: {exc}", file=sys.stderr)
        return 1
    clock = RealtimeClock(config.control_period) if args.realtime else LockstepClock()
    node = ControllerNode(config, bus, clock)
    try:
        report = node.run()
    except (ControllerError, FrameError, OSError) as exc:
        print(f"controller: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("controller: interrupted", file=sys.stderr)
        return 130
    finally:
        bus.shutdown()
    if args.report:
        write_report(report, args.report)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
