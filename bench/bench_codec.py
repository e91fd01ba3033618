"""Benchmark: a frame encoded and decoded by `rigbus.protocol.Protocol`, through the C codec's
plain case (`rigbus.ccodec`) and through the codec's Python path alone (SOFTHIL_CODEC=python, in
a child process), and what that makes of a 6-segment SYNC.

Per frame kind of the closed loop (the frames a 6-segment SYNC sends: some 27 each way, mostly
drive statuses, commands, controller states and camera markers), the best of --repeat batches
of microseconds per encode and per decode, then the SYNC's mix of frames (`SYNC_MIX`, counted in
the default task's loop) in microseconds each way. Compare with the SYNC's own time from
`bench_run.py --budget-only`; on a noisy host compare instruction counts instead
(`bench/instructions.py`, once with SOFTHIL_CODEC=python).

Run from the checkout: PYTHONPATH=. python bench/bench_codec.py [--repeat 200]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import timeit

from rigbus import ccodec
from rigbus.protocol import (
    CameraFrame,
    CameraMarker,
    ControllerState,
    DriveCommand,
    DriveStatus,
    Protocol,
    Sync,
)

FRAMES = {
    "DriveStatus": DriveStatus(3, 0.0123, 12345.0, -2340.0, 0, 17),
    "DriveCommand": DriveCommand(3, 0.031, True, 17),
    "ControllerState": ControllerState(3, 1.5, -2.25, 4),
    "CameraMarker": CameraMarker(2, 0.1234, -0.0456, 9, 0.002),
    "CameraFrame": CameraFrame(9, 0.002, 127, 7),
    "SYNC": Sync(5),
}
# frames of each kind a SYNC of the 6-segment default task encodes (and decodes), counted
SYNC_MIX = {
    "DriveStatus": 6,
    "DriveCommand": 5.9,
    "ControllerState": 5.9,
    "CameraMarker": 6.9,
    "CameraFrame": 1,
    "SYNC": 1,
}
NUMBER = 500  # calls per batch


def measure(repeat: int) -> dict[str, tuple[float, float]]:
    """(encode, decode) [us] per frame kind, the best batch of `repeat`."""
    protocol = Protocol()
    figures = {}
    for name, frame in FRAMES.items():
        message = protocol.encode(frame)
        protocol.decode(message)  # the first decoding makes the decoder
        encode = min(
            timeit.repeat(lambda f=frame: protocol.encode(f), number=NUMBER, repeat=repeat)
        )
        decode = min(
            timeit.repeat(lambda m=message: protocol.decode(m), number=NUMBER, repeat=repeat)
        )
        figures[name] = (encode / NUMBER * 1e6, decode / NUMBER * 1e6)
    return figures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=200, help="batches per figure (best taken)")
    parser.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.inner:
        print(json.dumps(measure(args.repeat)))
        return 0
    if ccodec.load() is None:
        print(f"bench_codec: no C codec here ({ccodec.failure()})")
        return 1
    python = subprocess.run(
        [sys.executable, __file__, "--inner", "--repeat", str(args.repeat)],
        env={**os.environ, ccodec.ENV: "python"},
        capture_output=True,
        text=True,
        check=True,
    )
    paths = {"C": measure(args.repeat), "Python": json.loads(python.stdout)}
    print(f"{'frame':>16s} {'C encode':>9s} {'decode':>7s} {'Python encode':>14s} {'decode':>7s}")
    for name in FRAMES:
        (ce, cd), (pe, pd) = paths["C"][name], paths["Python"][name]
        print(f"{name:>16s} {ce:9.2f} {cd:7.2f} {pe:14.2f} {pd:7.2f}  us")
    for path, figures in paths.items():
        total = sum(SYNC_MIX[n] * (e + d) for n, (e, d) in figures.items())
        print(f"a 6-segment SYNC's frames, {path}: {total:.0f} us encoded and decoded")
    return 0


if __name__ == "__main__":
    sys.exit(main())
