"""`python -m controllers`: the controller node as its own program (also `hil controller`).

It reads its configuration (written by `hil run` into the run folder), opens the bus and runs the
experiment as the SYNC producer. Errors print one line and exit 1.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can

from controllers import cukf
from controllers.config import read_config
from controllers.node import (
    ControllerError,
    ControllerNode,
    LockstepClock,
    RealtimeClock,
    write_report,
)
from rigbus import ccodec
from rigbus.canbus import BusOpenError, BusSpec, open_bus
from rigbus.protocol import FrameError

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


def _read_config(path: Path) -> Any:
    """The configuration file, or ValueError with one line naming what is wrong."""
    if path.is_dir():
        raise ValueError("is a folder, not a controller.json")
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ValueError("no such file") from None
    except OSError as exc:
        raise ValueError(f"cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ValueError("not UTF-8 text (not a controller.json)") from None
    if not text.strip():
        raise ValueError("empty (not a controller.json)")
    try:
        return read_config(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"not JSON: {exc}") from None
    except (KeyError, TypeError, RecursionError, OverflowError) as exc:
        raise ValueError(f"not a controller configuration ({type(exc).__name__}: {exc})") from None


def run(args: argparse.Namespace) -> int:
    try:
        ccodec.setting()
        cukf.setting()
    except ValueError as exc:
        print(f"controller: error: {exc}", file=sys.stderr)
        return 1
    try:
        config = _read_config(args.config)
    except ValueError as exc:
        print(f"controller: error: {args.config}: {exc}", file=sys.stderr)
        return 1
    try:
        bus = open_bus(BusSpec.parse(args.bus))
    except (BusOpenError, ValueError) as exc:
        print(f"controller: error: {exc}", file=sys.stderr)
        return 1
    clock = RealtimeClock(config.control_period) if args.realtime else LockstepClock()
    try:
        report = ControllerNode(config, bus, clock).run()
    except (ControllerError, FrameError, OSError, can.CanError) as exc:
        print(f"controller: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("controller: interrupted", file=sys.stderr)
        return 130
    finally:
        bus.shutdown()
    if report.intrusions:
        print(
            f"controller: warning: {report.intrusions} frame(s) from another node in this "
            f"controller's or a drive's name; first: {report.first_intrusion}",
            file=sys.stderr,
        )
    if args.report:
        try:
            write_report(report, args.report)
        except OSError as exc:
            print(f"controller: error: {args.report}: {exc.strerror or exc}", file=sys.stderr)
            return 1
    return 0


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text or type(exc).__name__


def main(argv: Sequence[str] | None = None) -> int:
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
