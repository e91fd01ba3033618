"""`hil bus`: bus tools. `serve` runs the loopback inter-process CAN hub in the foreground;
`up`/`down` manage a vcan interface; `dump`, `record`, `replay`, `send` and `load` work on a
live bus (a `--bus` spec as `hil run` takes) or a log file; the work is in `hil.bustools`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hil.bus import loopback
from hil.errors import HilError

DEFAULT_BUS = "loopback"
BUS_HELP = "bus spec: loopback[:HOST:PORT] (the hub of `hil bus serve`), socketcan:IFACE"


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli.parsers import example_parser

    parser = example_parser(
        commands,
        "bus",
        "CAN bus tools",
        "  hil bus serve                    loopback hub on 127.0.0.1:29536\n"
        "  hil bus dump                     decode the hub's traffic with the DBC\n"
        "  hil bus dump --log runs/x/can.log --message 'DriveStatus*'\n"
        "  hil bus record run.blf           record the hub's traffic (Ctrl-C stops)\n"
        "  hil bus replay can.log --direction R --lockstep\n"
        "  hil bus send loopback 080#05\n"
        "  hil bus load                     bus load of the default scenario\n"
        "  hil bus load --log runs/x/can.log\n",
    )
    sub = parser.add_subparsers(dest="bus_command", metavar="ACTION", required=True)
    serve = example_parser(
        sub,
        "serve",
        "serve the loopback CAN hub (socketcand and softhil's binary records) until Ctrl-C",
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
    serve.add_argument(
        "--max-clients",
        type=int,
        default=loopback.DEFAULT_MAX_CLIENTS,
        help="connections served at once; more are refused",
    )
    serve.add_argument(
        "--max-buffer",
        type=loopback.parse_byte_size,
        default="64M",
        metavar="BYTES",
        help="outgoing bytes buffered for all clients together (e.g. 64M, 512K); a client that "
        "stops reading beyond its equal share is disconnected",
    )
    serve.set_defaults(handler=_serve)
    load = example_parser(
        sub,
        "load",
        "bus load a scenario implies (from the DBC at its bitrate), or measured from a log or "
        "live traffic with per-message rates",
        "  hil bus load\n  hil bus load my.toml --bitrate 250000\n"
        "  hil bus load --log runs/default-1/can.log\n"
        "  hil bus load --bus loopback --seconds 5\n",
    )
    load.add_argument(
        "scenario", nargs="?", metavar="NAME|FILE", help="scenario NAME or FILE (default: built-in)"
    )
    load.add_argument(
        "--bitrate",
        type=int,
        help="bitrate [bit/s] (default: the scenario's, or 1000000 for --log/--bus)",
    )
    load.add_argument("--log", type=Path, help="measure the frames of this log instead")
    load.add_argument("--bus", help="measure live traffic on this bus spec instead")
    load.add_argument("--seconds", type=float, default=5.0, help="listening time for --bus")
    load.set_defaults(handler=_load)

    for name, help_text in (
        ("up", "create and bring up a vcan interface (needs SocketCAN)"),
        ("down", "remove a vcan interface"),
    ):
        action = example_parser(sub, name, help_text, f"  sudo hil bus {name} vcan0\n")
        action.add_argument("iface", nargs="?", default="vcan0", help="interface (vcan0)")
        action.set_defaults(handler=_vcan, vcan_action=name)

    dump = example_parser(
        sub,
        "dump",
        "print frames decoded with the DBC, one candump-style line each (Ctrl-C stops)",
        "  hil bus dump\n"
        "  hil bus dump --id 0x180-0x18F --id 080\n"
        "  hil bus dump --log can.log --message 'DriveCommand*' --count 10\n"
        "  hil bus dump --raw > copy.log\n",
    )
    _add_source(dump)
    _add_filters(dump)
    dump.add_argument("--raw", action="store_true", help="candump -L lines only, no decoding")
    dump.add_argument("--count", type=int, help="stop after N frames")
    dump.add_argument(
        "--timeout", type=float, help="stop after S seconds without a frame (live bus)"
    )
    dump.set_defaults(handler=_dump)

    record = example_parser(
        sub,
        "record",
        "record a bus into a log file, format by suffix: .log .asc .blf .trc .csv .mf4",
        "  hil bus record run.log\n  hil bus record run.blf --bus socketcan:vcan0\n",
    )
    record.add_argument("file", type=Path, help="log file to write")
    record.add_argument("--bus", default=DEFAULT_BUS, help=BUS_HELP)
    record.add_argument("--overwrite", action="store_true", help="replace an existing file")
    record.add_argument("--count", type=int, help="stop after N frames")
    record.add_argument("--timeout", type=float, help="stop after S seconds without a frame")
    record.set_defaults(handler=_record)

    replay = example_parser(
        sub,
        "replay",
        "transmit the frames of a log onto a bus, timed (--speed) or in lockstep by SYNC counter",
        "  hil bus replay can.log --speed 2\n"
        "  hil bus replay runs/x/can.log --direction R --lockstep   the controller's frames,\n"
        "      against a rig's plant (hil run brings its own controller)\n"
        "  hil bus replay runs/x/can.log --direction T --lockstep   the plant's frames, against\n"
        "      a controller started after it (hil controller)\n",
    )
    replay.add_argument("file", type=Path, help="log file (any python-can format)")
    replay.add_argument("--bus", default=DEFAULT_BUS, help=BUS_HELP)
    mode = replay.add_mutually_exclusive_group()
    mode.add_argument("--speed", type=float, default=1.0, help="time scale (2 = twice as fast)")
    mode.add_argument(
        "--lockstep",
        action="store_true",
        help="no timing: per SYNC cycle wait for the receiver's frames echoing the counter",
    )
    replay.add_argument(
        "--direction",
        choices=("R", "T", "all"),
        default="all",
        help="replay only frames the logging node received (R) or sent (T), or all",
    )
    replay.add_argument(
        "--timeout", type=float, default=2.0, help="lockstep: longest wait for one echo [s]"
    )
    _add_filters(replay)
    replay.set_defaults(handler=_replay)

    send = example_parser(
        sub,
        "send",
        "send one frame: cansend ID#DATA, or a DBC message from signal values",
        "  hil bus send loopback 080#05\n"
        "  hil bus send loopback 18FF1234#01.02.03\n"
        "  hil bus send socketcan:vcan0 123#R    remote frame (the loopback hub carries none)\n"
        "  hil bus send loopback --message DriveCommand1 piston_setpoint=0.05 enable=1 "
        "counter=3\n",
    )
    send.add_argument("spec", help="bus spec, e.g. loopback or socketcan:vcan0")
    send.add_argument("frame", nargs="?", help="ID#DATA (cansend syntax)")
    send.add_argument(
        "--message",
        nargs="+",
        metavar="NAME [SIGNAL=VALUE ...]",
        help="DBC message to encode, then every signal as name=value in physical units",
    )
    send.set_defaults(handler=_send)


def _add_source(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--bus", help=BUS_HELP)
    source.add_argument("--log", type=Path, help="read frames from this log file instead")


def _add_filters(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--id",
        action="append",
        metavar="ID",
        help="hex id (0x181) or range (0x180-0x18F), repeatable, comma lists ok",
    )
    parser.add_argument(
        "--message",
        action="append",
        metavar="NAME",
        help="DBC message name, glob ok (DriveStatus*), repeatable",
    )


# the hub's setting names, as `hil bus serve` spells them
SERVE_FLAGS = (
    ("max_buffer_bytes", "--max-buffer"),
    ("max_clients", "--max-clients"),
    ("allow_remote=True (CLI: --allow-remote)", "--allow-remote"),
    ("hub port", "--port"),
    ("hub host", "--host"),
)


def _serve(args: argparse.Namespace) -> int:
    try:
        return loopback.serve(
            args.host,
            args.port,
            allow_remote=args.allow_remote,
            max_clients=args.max_clients,
            max_buffer_bytes=args.max_buffer,
        )
    except loopback.HubSettingError as exc:
        text = str(exc)
        for name, flag in SERVE_FLAGS:
            text = text.replace(name, flag)
        raise HilError(text) from None


def _load(args: argparse.Namespace) -> int:
    if args.log is not None or args.bus is not None:
        return _measured_load(args)
    from dataclasses import replace

    from hil.bustools.load import check_bitrate
    from hil.scenario import load_scenario, resolve_scenario
    from hil.summary import BUS_LOAD_WARNING, bus_load_of
    from rigbus.protocol import Protocol

    scenario = load_scenario(resolve_scenario(args.scenario) if args.scenario else None)
    if args.bitrate is not None:
        check_bitrate(args.bitrate)
    if args.bitrate:
        scenario = replace(scenario, bus=replace(scenario.bus, bitrate=args.bitrate))
    load = bus_load_of(scenario, Protocol())
    print(
        f"{scenario.name}: bus load {100 * load:.1f} % at {scenario.bus.bitrate / 1000:g} kbit/s "
        "(worst-case bit stuffing)"
    )
    if load > BUS_LOAD_WARNING:
        print(
            f"warning: above {100 * BUS_LOAD_WARNING:.0f} %: frames will be delayed on a real bus"
        )
    return 0


def _measured_load(args: argparse.Namespace) -> int:
    from hil.bustools.dump import live_frames
    from hil.bustools.frames import load_database, open_spec
    from hil.bustools.load import check_bitrate, measure
    from hil.bustools.logs import iter_log

    if args.scenario is not None:
        raise HilError("give a scenario, or --log/--bus, not both")
    if args.log is not None and args.bus is not None:
        raise HilError("give --log or --bus, not both")
    bitrate = 1_000_000 if args.bitrate is None else args.bitrate
    check_bitrate(bitrate)
    database = load_database()
    if args.log is not None:
        report = measure(iter_log(args.log), database, bitrate)
    else:
        import time

        _check_wait("--seconds", args.seconds, positive=True)
        bus = open_spec(args.bus)
        try:
            end = time.monotonic() + args.seconds
            frames = []
            for msg in live_frames(bus, idle_timeout=args.seconds):
                frames.append(msg)
                if time.monotonic() >= end:
                    break
        finally:
            bus.shutdown()
        report = measure(frames, database, bitrate, span=args.seconds)
    print("\n".join(report.lines()))
    return 0


def _vcan(args: argparse.Namespace) -> int:
    from hil.bustools import vcan

    if not vcan.socketcan_available():  # an error like any other (exit 1; 2 is wrong usage)
        raise HilError(
            f"this kernel has no SocketCAN (AF_CAN), so no {args.iface}; {vcan.LOOPBACK_HINT}"
        )
    action = vcan.up if args.vcan_action == "up" else vcan.down
    print(action(args.iface))
    return 0


def _frames_of(args: argparse.Namespace):  # noqa: ANN202 - (frames, bus or None)
    from hil.bustools.dump import live_frames
    from hil.bustools.frames import open_spec
    from hil.bustools.logs import iter_log

    if args.log is not None:
        return iter_log(args.log), None
    bus = open_spec(DEFAULT_BUS if args.bus is None else args.bus)
    return live_frames(bus, args.timeout), bus


MAX_WAIT = 86_400.0  # [s] the longest wait a bus tool takes: a day
MIN_SPEED = 1e-6  # the slowest replay: a millionth of real time (a wait must fit a sleep)


def _check_wait(flag: str, value: float | None, positive: bool = False) -> None:
    """HilError unless `value` (None: not given) is a number of seconds in [0, a day], or
    (0, a day] if `positive`: a negative, NaN or endless wait reached python-can as a
    traceback, or never ended."""
    if value is None:
        return
    if not ((value > 0 if positive else value >= 0) and value <= MAX_WAIT):
        low = "above 0" if positive else "at least 0"
        raise HilError(f"{flag} must be {low} and at most {MAX_WAIT:g} s (a day), got {value:g}")


def _check_count(value: int | None) -> None:
    if value is not None and value <= 0:
        raise HilError(f"--count must be positive, got {value}")


def _dump(args: argparse.Namespace) -> int:
    from hil.bustools.dump import DumpCount, dump, print_count
    from hil.bustools.frames import FrameFilter, load_database
    from hil.bustools.logs import has_direction

    _check_count(args.count)
    _check_wait("--timeout", args.timeout)
    database = load_database()
    selection = FrameFilter.parse(args.id or [], args.message or [], database)
    frames, bus = _frames_of(args)
    tally = DumpCount(raw=args.raw)
    try:
        directed = not args.log or has_direction(args.log)
        dump(frames, database, selection, args.raw, args.count, sys.stdout, tally, directed)
    except KeyboardInterrupt:
        pass
    finally:
        if bus is not None:
            bus.shutdown()
    print_count(tally)
    return 0


def _record(args: argparse.Namespace) -> int:
    from hil.bustools.frames import open_spec
    from hil.bustools.logs import check_format_available
    from hil.bustools.record import record

    _check_count(args.count)
    _check_wait("--timeout", args.timeout)
    if args.file.is_dir():  # '' is '.' by then
        raise HilError(
            f"{args.file}: is a folder; name the log file (e.g. {args.file / 'run.log'})"
        )
    check_format_available(args.file)
    if args.file.exists() and not args.overwrite:
        raise HilError(f"{args.file}: exists; pass --overwrite to replace it")
    bus = open_spec(args.bus)
    try:
        print(f"recording {args.bus} into {args.file} (Ctrl-C stops)", file=sys.stderr)
        written = record(bus, args.file, args.overwrite, args.count, args.timeout)
    finally:
        bus.shutdown()
    print(f"recorded {written} frames into {args.file}", file=sys.stderr)
    return 0


def _replay(args: argparse.Namespace) -> int:
    from hil.bustools.frames import FrameFilter, load_database, open_spec
    from hil.bustools.logs import DIRECTED, has_direction, read_log
    from hil.bustools.replay import check_lockstep_direction, replay_lockstep, replay_timed

    database = load_database()
    selection = FrameFilter.parse(args.id or [], args.message or [], database)
    if args.lockstep and not has_direction(args.file):
        raise HilError(
            f"{args.file}: --lockstep replays one side of the log (--direction R or T), which a "
            f".csv log does not record; replay it timed (--speed), or use a {DIRECTED} log"
        )
    if args.direction != "all" and not has_direction(args.file):
        raise HilError(
            f"{args.file}: a .csv log has no direction column, so --direction {args.direction} "
            f"cannot choose its frames; use --direction all, or a {DIRECTED} log"
        )
    messages = read_log(args.file)
    if not args.lockstep and not args.speed >= MIN_SPEED:
        raise HilError(f"--speed must be at least {MIN_SPEED:g} (inf: no waits), got {args.speed}")
    if args.lockstep:
        check_lockstep_direction(args.direction)
        _check_wait("--timeout", args.timeout, positive=True)
    bus = open_spec(args.bus)
    try:
        if args.lockstep:
            tally = replay_lockstep(
                bus, messages, args.direction, selection, database, args.timeout
            )
        else:
            tally = replay_timed(bus, messages, args.direction, selection, args.speed)
    finally:
        bus.shutdown()
    print(tally.line(), file=sys.stderr)
    return 0


def _send(args: argparse.Namespace) -> int:
    from hil.bustools.frames import load_database, open_spec
    from hil.bustools.send import encode_message, parse_cansend, send_one

    if args.message is not None:
        if args.frame is not None:
            raise HilError("give ID#DATA or --message NAME sig=value ..., not both")
        msg = encode_message(load_database(), args.message[0], args.message[1:])
    else:
        if args.frame is None:
            raise HilError(
                "give one frame as ID#DATA (cansend syntax), or --message NAME sig=value"
            )
        msg = parse_cansend(args.frame)
    bus = open_spec(args.spec, flag=None)
    try:
        send_one(bus, msg)
    finally:
        bus.shutdown()
    return 0
