"""`hil controller`: the controller node program (the same as `python -m controllers`)."""

from __future__ import annotations

import argparse

from hil.seam import controller_program


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli.parsers import example_parser

    parser = example_parser(
        commands,
        "controller",
        "run the controller node: SYNC producer and curvature control over CAN",
        "  hil controller --config runs/default-1/controller.json --bus loopback:29536\n"
        "  hil controller --config controller.json --bus socketcan:vcan0 --realtime\n"
        "  (against the simulated rig: hil run --controller external prints this command line\n"
        "   with its bus, then waits for it; against a recorded plant: hil bus serve, then\n"
        "   hil bus replay runs/default-1/can.log --direction T --lockstep --timeout 10\n"
        "   --bus loopback:127.0.0.1:29536, then this)\n",
    )
    program = controller_program()
    program.add_arguments(parser)
    parser.set_defaults(handler=program.run)
