"""A controller of your own: python-can, cantools and the DBC, nothing from softhil.

It drives every drive cylinder's piston through a sine about mid-stroke, open loop, in the
lockstep protocol of the DBC (docs/sync-cycle.md): send SYNC(c), collect each drive's
DriveStatus echoing c (the drives answer last, after the camera's frames), send a DriveCommand
to each drive, and SYNC again; after the final SYNC nothing acts. It reads the run's
controller.json only for the number of cycles, the control period and the stroke.

    hil run --controller 'python examples/piston_sine.py --config {config}
        --interface {interface} --channel {channel} --host {host} --port {port}'

Any python-can interface works: on a rig, --interface pcan --channel PCAN_USBBUS1.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import can
import cantools

# the protocol: what hil run gives its programs (SOFTHIL_DBC, also the {dbc} placeholder), or
# the checkout's when run by hand beside it
DBC = os.environ.get("SOFTHIL_DBC") or Path(__file__).resolve().parents[1] / "rigbus/softhil.dbc"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, type=Path, help="the run's controller.json")
    parser.add_argument("--interface", default="socketcand")
    parser.add_argument("--channel", default="softhil")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=29536)
    parser.add_argument("--dbc", type=Path, default=DBC, help="the DBC file (default: %(default)s)")
    parser.add_argument("--amplitude", type=float, default=0.4, help="of the half stroke")
    parser.add_argument("--offset", type=float, default=0.0, help="of the half stroke")
    parser.add_argument("--frequency", type=float, default=1.0, help="[Hz]")
    parser.add_argument("--timeout", type=float, default=5.0, help="[s] per cycle")
    args = parser.parse_args(argv)

    config = json.loads(args.config.read_text())
    period, cycles = config["control_period"], config["cycles"]
    x_min, x_max = config["x_min"], config["x_max"]
    drives = len(x_min)
    db = cantools.database.load_file(args.dbc)
    sync = db.get_message_by_name("SYNC")
    status = {db.get_message_by_name(f"DriveStatus{i}").frame_id: i for i in range(1, drives + 1)}
    command = [db.get_message_by_name(f"DriveCommand{i}") for i in range(1, drives + 1)]
    kwargs = {}
    if args.interface == "socketcand":  # tcp_tune: no Nagle, or each SYNC waits 40 ms for an ACK
        kwargs = {"host": args.host, "port": args.port, "tcp_tune": True}
    with can.Bus(interface=args.interface, channel=args.channel, **kwargs) as bus:
        for cycle in range(cycles + 1):
            counter = cycle % 256
            bus.send(can.Message(arbitration_id=sync.frame_id, data=sync.encode(
                {"counter": counter}), is_extended_id=False))  # fmt: skip
            waiting = set(range(drives))
            deadline = time.monotonic() + args.timeout
            while waiting:
                message = bus.recv(timeout=max(0.0, deadline - time.monotonic()))
                if message is None:
                    print(
                        f"no DriveStatus for SYNC {cycle} within {args.timeout} s", file=sys.stderr
                    )
                    return 1
                drive = status.get(message.arbitration_id)
                if (
                    drive is not None
                    and db.decode_message(message.arbitration_id, message.data)["counter"]
                    == counter
                ):
                    waiting.discard(drive - 1)
            if cycle == cycles:
                break  # the final SYNC takes the plant to the end; nothing acts after it
            t = (cycle + 1) * period  # the commands act from the next SYNC
            for i, message in enumerate(command):
                middle, half = (x_min[i] + x_max[i]) / 2, (x_max[i] - x_min[i]) / 2
                wave = args.offset + args.amplitude * math.sin(2 * math.pi * args.frequency * t)
                x = middle + wave * half
                data = message.encode({"piston_setpoint": x, "enable": 1, "counter": counter})
                bus.send(can.Message(arbitration_id=message.frame_id, data=data,
                                     is_extended_id=False))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
