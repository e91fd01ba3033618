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
  ``{realtime}`` ``1`` if the run is paced by the wall clock, else ``0``; ``{dbc}`` the protocol's
  DBC file (softhil's ``rigbus/softhil.dbc``), for a program that decodes with it.
  ``{{`` and ``}}`` are literal braces; nothing else goes inside braces (no format specs, no
  indexing). Paths are absolute. The same values are in the program's environment as
  ``SOFTHIL_CONFIG``, ``SOFTHIL_REPORT``, ``SOFTHIL_BUS``, ``SOFTHIL_INTERFACE``,
  ``SOFTHIL_CHANNEL``, ``SOFTHIL_HOST``, ``SOFTHIL_PORT``, ``SOFTHIL_REALTIME`` and
  ``SOFTHIL_DBC``.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import IO

from hil.errors import HilError
from rigbus.canbus import HUB_KINDS, BusSpec
from rigbus.protocol import DBC_PATH

SOFTHIL = "softhil"
USER_LINGER = 5.0  # [s] a user's program has after the final SYNC to exit, before it is stopped
EXTERNAL = "external"
PLACEHOLDERS = (
    "config",
    "report",
    "bus",
    "interface",
    "channel",
    "host",
    "port",
    "realtime",
    "dbc",
)


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
        "dbc": str(DBC_PATH.resolve()),
    }


# in a word of a command line: {{, }}, a placeholder {name}, or any other brace (an error)
_BRACES = re.compile(r"\{\{|\}\}|\{([A-Za-z_][A-Za-z0-9_]*)\}|[{}]")


def user_command(
    template: str, values: Mapping[str, str], option: str = "--controller"
) -> list[str]:
    """The user's command line `template` with its placeholders replaced; HilError naming
    `option` for a line that cannot be split, is empty, holds an unknown placeholder or a
    brace that is neither a placeholder's nor doubled."""
    try:
        words = shlex.split(template)
    except ValueError as exc:  # an unclosed quote
        raise HilError(f"{option}: cannot split {template!r}: {exc}") from None
    if not words:
        raise HilError(f"{option}: an empty command")
    known = ", ".join(f"{{{name}}}" for name in PLACEHOLDERS)

    def replace(match: re.Match[str]) -> str:
        text, name = match.group(0), match.group(1)
        if text in ("{{", "}}"):
            return text[0]
        if name is None:
            raise HilError(
                f"{option}: a stray {text!r} in {template!r} (placeholders: {known}; {{{{ and "
                "}} are literal braces)"
            )
        if name not in values:
            raise HilError(
                f"{option}: unknown placeholder {{{name}}} in {template!r} (known: {known}; "
                "{{ and }} are literal braces)"
            )
        return values[name]

    return [_BRACES.sub(replace, word) for word in words]


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
    if program.startswith("~") or "$" in program:
        raise HilError(
            f"{option}: cannot start {program!r}: no shell runs the command, so ~ and $VARIABLES "
            "are not expanded (write the path, or run it through sh -c '...')"
        )
    if os.sep in program:
        if not (os.path.isfile(program) and os.access(program, os.X_OK)):
            what = "not an executable file" if os.path.exists(program) else "no such file"
            raise HilError(f"{option}: cannot start {program!r}: {what}")
    elif shutil.which(program) is None:
        here = f" (the file here is ./{program})" if os.path.isfile(program) else ""
        raise HilError(f"{option}: cannot start {program!r}: not found on PATH{here}")


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
        # a session (and process group) of its own: stop() ends a shell's children with it
        return subprocess.Popen(
            command, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True
        )
    except OSError as exc:  # not found, not executable
        raise HilError(
            f"--controller: cannot start {command[0]!r}: {exc.strerror or exc}"
        ) from None


def _signal_group(process: subprocess.Popen[bytes], sig: int) -> bool:
    """Send `sig` to the process group `start` gave `process`; False if none is left."""
    try:
        os.killpg(process.pid, sig)
    except (ProcessLookupError, PermissionError):
        return False
    return True


def group_alive(process: subprocess.Popen[bytes]) -> bool:
    """Whether any process of the group `start` gave `process` is left (its own included), not
    counting zombies (in a container, init may never reap the orphans it adopts)."""
    if not _signal_group(process, 0):
        return False
    try:
        entries = os.listdir("/proc")
    except OSError:  # no procfs: the signal's answer
        return True
    for entry in entries:
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        # pid (comm) state ppid pgrp ...: comm may hold spaces and parentheses
        state, _ppid, group = stat.rpartition(")")[2].split()[:3]
        if int(group) == process.pid and state not in "ZX":
            return True
    return False


def stop(process: subprocess.Popen[bytes], grace: float = 5.0) -> str | None:
    """Stop a program `start` started, with every process of its group (a shell's children,
    a background job): SIGTERM (and SIGCONT, for a stopped one), then SIGKILL to what is left
    after `grace` seconds. Returns how its own process ended: None if it had exited already,
    else "SIGTERM" or "SIGKILL"."""
    running = process.poll() is None
    if not _signal_group(process, signal.SIGTERM):
        process.wait()
        return None
    _signal_group(process, signal.SIGCONT)
    how: str | None = None
    deadline = time.monotonic() + grace
    if running:
        try:
            process.wait(timeout=grace)
            how = "SIGTERM"
        except subprocess.TimeoutExpired:
            how = "SIGKILL"
    while how != "SIGKILL" and time.monotonic() < deadline and group_alive(process):
        time.sleep(0.02)  # the rest of the group, ending on SIGTERM
    _signal_group(process, signal.SIGKILL)
    process.wait()
    return how


# python-can's warning from a bus object collected without shutdown(): printed after the
# program's own last words when it dies of an error
_NOT_SHUT_DOWN = re.compile(r"^\S+ was not properly shut down$")
# characters a terminal would act on
_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")


def last_words(log: Path | None, limit: int = 200) -> str:
    """The last line a program wrote into `log` that says something (not python-can's shutdown
    warning), without control characters, at most `limit` characters; "" if none."""
    if log is None or not log.is_file():
        return ""
    with log.open("rb") as f:
        f.seek(max(0, log.stat().st_size - 64 * 1024))
        text = f.read().decode(errors="replace")
    for line in reversed(text.splitlines()):
        line = _CONTROL.sub("", line).strip()
        if line and not _NOT_SHUT_DOWN.match(line):
            return line if len(line) <= limit else line[: limit - 3] + "..."
    return ""
