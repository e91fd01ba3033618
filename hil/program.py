"""The controller program a run or a replay starts: softhil's own, a user's, or none.

`hil run --controller` and `hil replay --controller` take

* ``softhil`` (the default): softhil's controller program (`python -m controllers`);
* ``external`` (`hil run` only): no program; the run waits for a controller started by hand on
  its bus, which sends SYNC(0) within ``--wait`` seconds;
* anything else: a command line, split as a POSIX shell would (no shell runs it), with these
  placeholders replaced in each word:

  ``{config}`` the run's controller.json; ``{report}`` where the program may write its report
  (JSON, optional); ``{bus}`` the bus as softhil's spec (``softhil:127.0.0.1:PORT``, what
  ``hil controller --bus`` takes); ``{interface}``, ``{channel}``, ``{host}``, ``{port}`` the
  same bus as python-can's arguments (for the run's own hub: python-can's ``socketcand``
  interface, which the hub speaks on the same port; an empty host and port off the hub);
  ``{realtime}`` ``1`` if the run is paced by the wall clock, else ``0``.
  ``{{`` and ``}}`` are literal braces. The same values are in the program's environment as
  ``SOFTHIL_CONFIG``, ``SOFTHIL_REPORT``, ``SOFTHIL_BUS``, ``SOFTHIL_INTERFACE``,
  ``SOFTHIL_CHANNEL``, ``SOFTHIL_HOST``, ``SOFTHIL_PORT`` and ``SOFTHIL_REALTIME``.
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import IO

from controllers.canbus import HUB_KINDS, BusSpec
from hil.errors import HilError

SOFTHIL = "softhil"
USER_LINGER = 5.0  # [s] a user's program has after the final SYNC to exit, before it is stopped
EXTERNAL = "external"
PLACEHOLDERS = ("config", "report", "bus", "interface", "channel", "host", "port", "realtime")


def softhil_command(config: Path, bus: BusSpec, report: Path | None, realtime: bool) -> list[str]:
    """softhil's own controller program for `config` on `bus`."""
    command = [sys.executable, "-m", "controllers", "--config", str(config), "--bus", str(bus)]
    if report is not None:
        command += ["--report", str(report)]
    if realtime:
        command.append("--realtime")
    return command


def placeholder_values(
    config: Path, bus: BusSpec, report: Path | None, realtime: bool
) -> dict[str, str]:
    """What each placeholder stands for (also the program's SOFTHIL_* environment)."""
    if bus.kind in HUB_KINDS:  # the loopback hub speaks socketcand on its port, for any client
        interface, host, port = "socketcand", bus.host, str(bus.port)
    else:
        interface, host, port = bus.kind, "", ""
    return {
        "config": str(config),
        "report": "" if report is None else str(report),
        "bus": str(bus),
        "interface": interface,
        "channel": bus.channel or "",
        "host": host,
        "port": port,
        "realtime": "1" if realtime else "0",
    }


def user_command(
    template: str, values: Mapping[str, str], option: str = "--controller"
) -> list[str]:
    """The user's command line `template` with its placeholders replaced; HilError naming
    `option` for a line that cannot be split, is empty, or holds an unknown placeholder."""
    try:
        words = shlex.split(template)
    except ValueError as exc:  # an unclosed quote
        raise HilError(f"{option}: cannot split {template!r}: {exc}") from None
    if not words:
        raise HilError(f"{option}: an empty command")
    known = ", ".join(f"{{{name}}}" for name in PLACEHOLDERS)
    command = []
    for word in words:
        try:
            command.append(word.format_map(values))
        except KeyError as exc:
            raise HilError(
                f"{option}: unknown placeholder {{{exc.args[0]}}} in {template!r} (known: {known}; "
                "{{ and }} are literal braces)"
            ) from None
        except (ValueError, IndexError, AttributeError) as exc:
            raise HilError(
                f"{option}: {word!r} in {template!r}: {exc} (placeholders: {known}; {{{{ and "
                "}} are literal braces)"
            ) from None
    return command


def check_controller(
    template: str, option: str = "--controller", external: bool = True, what: str = "a replay"
) -> None:
    """Refuse a `--controller` that cannot be run, before anything is written (`external` only
    where it is allowed; `what` names the command that starts its controller)."""
    if template in (SOFTHIL, EXTERNAL) and (external or template == SOFTHIL):
        return
    if template == EXTERNAL:
        raise HilError(
            f"{option} external: {what} starts its controller; give its command line instead"
        )
    example = placeholder_values(Path("controller.json"), BusSpec("softhil", "c"), None, False)
    program = user_command(template, example, option)[0]
    if "{" in shlex.split(template)[0]:
        return  # named by a placeholder: known when it starts
    if os.sep in program:
        if not (os.path.isfile(program) and os.access(program, os.X_OK)):
            what = "not an executable file" if os.path.exists(program) else "no such file"
            raise HilError(f"{option}: cannot start {program!r}: {what}")
    elif shutil.which(program) is None:
        raise HilError(f"{option}: cannot start {program!r}: not found on PATH")


def environment(values: Mapping[str, str]) -> dict[str, str]:
    """The placeholders as the program's SOFTHIL_* environment variables."""
    return {f"SOFTHIL_{name.upper()}": value for name, value in values.items()}


def start(
    controller: str, config: Path, bus: BusSpec, report: Path, realtime: bool, log: IO[bytes]
) -> subprocess.Popen[bytes]:
    """Start `controller` (SOFTHIL or a user's command line) for `config` on `bus`, its output
    into `log`; HilError naming the program if it cannot start."""
    values = placeholder_values(config, bus, report, realtime)
    if controller == SOFTHIL:
        command = softhil_command(config, bus, report, realtime)
    else:
        command = user_command(controller, values)
    # the controller's matrices are at most 2N x 2N (N segments): BLAS threads would only spin
    # against the plant and the hub on the cores they share (6 segments: RTF 0.63 -> 0.80 on a
    # loaded 2-core machine); a user's own setting wins
    env = {"OPENBLAS_NUM_THREADS": "1", **os.environ, "PYTHONUNBUFFERED": "1"}
    env.update(environment(values))
    try:
        return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)
    except OSError as exc:  # not found, not executable
        raise HilError(
            f"--controller: cannot start {command[0]!r}: {exc.strerror or exc}"
        ) from None
