"""A run's controller as the plant sees it: a thread, a process, or one started by hand.

`start_controller` starts the controller a run talks to over its bus (softhil's in a thread
with `--inprocess` on a virtual bus, softhil's or a user's program as a process, or none for
`--controller external`), and the `ControllerPeer` it returns answers the two questions the
run asks: is it gone (`gone`, while the plant serves SYNCs) and what did it report (`finish`,
after the final SYNC). Invariant: a program the run started is stopped with its process group
whatever ends the run, and its report enters summary.json only as a JSON object (a user's
checked: `_checked_report`).
"""

from __future__ import annotations

import json
import math
import shlex
import subprocess
import threading
import time
from contextlib import ExitStack
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil.bus.hosted import HostedBus
from hil.errors import HilError
from hil.plant import STARTUP_TIMEOUT
from hil.program import (
    EXTERNAL,
    SOFTHIL,
    USER_LINGER,
    group_alive,
    last_words,
    placeholder_values,
    start,
)
from hil.program import stop as stop_program
from hil.results import ResultsFolder, note, write_file
from hil.run_bus import open_spec
from hil.seam import ControllerError, ControllerNode, LockstepClock, RealtimeClock
from rigbus.canbus import BusSpec
from rigbus.robots import RobotConfig

if TYPE_CHECKING:
    from hil.run import RunOptions

FINISH_TIMEOUT = 30.0  # [s] softhil's controller has after the final SYNC to exit
# [s] the connection that sent the SYNCs may stay closed before the controller is taken for
# gone: a program's exit shows first (with its code), a controller that reconnects resumes
CLOSED_GRACE = 1.0
# [s] the same for a program this run started: its exit code is due, and names what happened
# (a loaded host can take seconds to reap a program that ends on a signal)
PROCESS_CLOSED_GRACE = 15.0
MAX_REPORT_BYTES = 1 << 20  # a user program's report in summary.json: at most 1 MiB
MAX_REPORT_DEPTH = 32  # and at most this deep (json and the summary's writer recurse)
# the controller report's entries that the summary counts with, as ControllerReport has them
REPORT_NUMBERS = (
    "cycles",
    "status_missed",
    "stale_frames",
    "unknown_frames",
    "intrusions",
    "overruns",
    "max_lateness",
    "mean_lateness",
)


class ControllerPeer:
    """The controller, as a thread or a process, with one way to ask whether it is gone."""

    def __init__(self) -> None:
        self.process: subprocess.Popen[bytes] | None = None
        self.thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.report: Any = None
        self.log: Path | None = None
        self.user = False  # a user's program (its report is optional and checked)
        self.warnings: list[str] = []  # for summary.json
        self.failure: str | None = None  # a program that exited non-zero after the final SYNC
        self.hub: HostedBus | None = None  # the hub the plant hosts, watching the SYNC sender
        self._closed_since: float | None = None

    def gone(self) -> str | None:
        """Why the controller is gone, or None: its process exited, its thread stopped, or
        (with the hub the plant hosts, for a controller started by hand too) the connection
        that sent the SYNCs has been closed for CLOSED_GRACE without another sending them."""
        if self.process is not None:
            code = self.process.poll()
            if code is not None:  # a success that comes early is not one: say so
                early = " before the run's final SYNC" if code == 0 else ""
                return f"the controller exited with code {code}{early}{self._last_words()}"
        if self.thread is not None and not self.thread.is_alive():
            return (
                f"the controller stopped: {self.error}" if self.error else "the controller stopped"
            )
        where = self.hub.sender_gone() if self.hub is not None else None
        if where is None:
            self._closed_since = None
            return None
        now = time.monotonic()
        if self._closed_since is None:
            self._closed_since = now
        grace = PROCESS_CLOSED_GRACE if self.process is not None else CLOSED_GRACE
        if now - self._closed_since < grace:
            return None  # a program that exits is named by its exit code; one may reconnect
        return (
            f"the controller's connection to the run's hub ({where}, which sent the SYNCs) closed"
        )

    def _last_words(self) -> str:
        words = last_words(self.log)
        return f" ({words})" if words else ""

    def stop(self) -> str | None:
        """Stop the program and its process group (see hil.program.stop); how it ended."""
        how = None
        if self.process is not None:
            how = stop_program(self.process)
            if self.log is not None:
                self.log.with_name("controller.pid").unlink(missing_ok=True)
        return how

    def finish(self) -> dict[str, Any]:
        """Wait for a controller that has done its last cycle; its report. softhil's must
        exit within FINISH_TIMEOUT; a user's program that has not exited USER_LINGER seconds
        after the final SYNC (one that serves until it is stopped) is stopped, with a warning."""
        if self.process is not None:
            return self._finish_process(self.process)
        if self.thread is not None:
            return self._finish_thread(self.thread)
        return {}

    def _finish_process(self, process: subprocess.Popen[bytes]) -> dict[str, Any]:
        """The program's report once it has exited; a non-zero exit is kept as `failure`."""
        code = self._exit_code(process)
        if self.log is not None:
            self.log.with_name("controller.pid").unlink(missing_ok=True)
        if code != 0:  # after the final SYNC: the run is whole, scored, and then failed
            self.failure = (
                f"the controller failed with code {code} after the final SYNC{self._last_words()}"
            )
        return self._program_report()

    def _exit_code(self, process: subprocess.Popen[bytes]) -> int:
        """The program's exit code, once it has exited; a user's program still serving after
        USER_LINGER is stopped and counts as 0 (with a warning), softhil's after FINISH_TIMEOUT
        is an error. Processes it left behind are stopped, with a warning."""
        timeout = USER_LINGER if self.user else FINISH_TIMEOUT
        try:
            code = process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            how = self.stop()
            if not self.user:
                raise HilError(
                    f"the controller did not exit within {timeout:g} s of the final "
                    f"SYNC; stopped it{self._last_words()}"
                ) from None
            ended = "SIGTERM" if how == "SIGTERM" else "SIGTERM, then SIGKILL"
            self.warnings.append(
                f"the controller program had not exited {timeout:g} s after the final "
                f"SYNC; the run stopped it ({ended})"
            )
            return 0
        if group_alive(process):  # its own process is gone, children it left not
            self.stop()
            self.warnings.append(
                "the controller program left processes running after it exited; the "
                "run stopped them"
            )
        return code

    def _program_report(self) -> dict[str, Any]:
        """controller_report.json as summary.json takes it: softhil's whole (an error if it is
        not an object), a user's checked, or left out with a note; {} if there is none."""
        path = self.log.with_name("controller_report.json") if self.log else None
        if not (path and path.is_file() and path.stat().st_size):
            return {}
        report = self._load_report(path)
        if isinstance(report, dict):
            return _checked_report(report, path) if self.user else report
        if not self.user:
            raise HilError(f"{path}: not the controller's report: {report}")
        note(f"{path}: not a JSON object ({report}); the summary leaves it out")
        return {}

    def _load_report(self, path: Path) -> Any:
        """The report's JSON value, or the error that refuses it (a user's program's report is
        bounded in size and depth)."""
        size = path.stat().st_size
        try:
            if self.user and size > MAX_REPORT_BYTES:
                raise ValueError(f"{size} bytes, more than {MAX_REPORT_BYTES}")
            report = json.loads(path.read_text(errors="replace"))
            if self.user and _depth(report) > MAX_REPORT_DEPTH:
                raise ValueError(f"nested deeper than {MAX_REPORT_DEPTH} levels")
        except (ValueError, RecursionError) as exc:
            return exc
        return report

    def _finish_thread(self, thread: threading.Thread) -> dict[str, Any]:
        """The controller thread's report once it has finished; its failure as an error."""
        thread.join(timeout=30)
        if thread.is_alive():
            raise HilError("the controller thread did not finish within 30 s of the last SYNC")
        if self.error is not None:
            raise HilError(f"the controller failed: {self.error}")
        return asdict(self.report) if self.report is not None else {}


def _depth(value: Any) -> int:
    """How deep JSON `value` nests (a scalar: 0), without recursion."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        item, level = stack.pop()
        if isinstance(item, dict | list):
            deepest = max(deepest, level + 1)
            stack.extend(
                (v, level + 1) for v in (item.values() if isinstance(item, dict) else item)
            )
    return deepest


def _checked_report(report: dict[str, Any], path: Path) -> dict[str, Any]:
    """A user program's report, kept whole in the summary; the entries the summary counts with
    (softhil's names) only if they are finite numbers, and `realtime` only with its figures."""
    for key in REPORT_NUMBERS:
        value = report.get(key)
        if key in report and (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
            or value < 0
        ):
            note(f"{path}: {key} = {value!r} is not a count or a time; the summary leaves it out")
            del report[key]
    if report.get("realtime") and not all(
        k in report for k in ("overruns", "max_lateness", "mean_lateness")
    ):
        note(f"{path}: realtime without overruns, max_lateness and mean_lateness; left out")
        del report["realtime"]
    return report


def start_controller(
    config: RobotConfig,
    spec: BusSpec,
    options: RunOptions,
    folder: ResultsFolder,
    stack: ExitStack,
) -> ControllerPeer:
    """Start the run's controller on `spec` as `options` say: softhil's in a thread
    (`inprocess`), none (`external`: a note says how to start one), or a program whose
    controller.log, controller_report.json and controller.pid are the folder's."""
    if options.inprocess:
        return _start_thread(config, spec, options.realtime, stack)
    peer = ControllerPeer()
    out = folder.out.absolute()  # a program may change its working folder
    config_path, report = out / "controller.json", out / "controller_report.json"
    values = placeholder_values(config_path, spec, report, options.realtime)
    if options.controller == EXTERNAL:
        wait = STARTUP_TIMEOUT if options.wait is None else options.wait
        where = (
            f" ({values['interface']} {values['host']}:{values['port']}, channel "
            f"{values['channel']})"
            if values["port"]
            else ""
        )
        line = ["hil", "controller", "--config", str(config_path), "--bus", str(spec)]
        note(
            f"waiting {wait:g} s for a controller to send SYNC(0) on {spec}{where}; softhil's: "
            + shlex.join(line + (["--realtime"] if options.realtime else []))
        )
        return peer  # alive until the run ends or the bus falls silent
    peer.log = folder.claim("controller.log")
    folder.claim("controller_report.json")
    peer.user = options.controller != SOFTHIL
    log = stack.enter_context(peer.log.open("wb"))
    peer.process = start(options.controller, config_path, spec, report, options.realtime, log)
    stack.callback(peer.stop)
    write_file(folder.claim("controller.pid"), f"{peer.process.pid}\n")
    return peer


def _start_thread(
    config: RobotConfig, spec: BusSpec, realtime: bool, stack: ExitStack
) -> ControllerPeer:
    """softhil's controller in a thread of this process, on its own connection to `spec`."""
    peer = ControllerPeer()
    bus = open_spec(spec)
    stack.callback(bus.shutdown)
    clock = RealtimeClock(config.control_period) if realtime else LockstepClock()
    node = ControllerNode(config, bus, clock)

    def work() -> None:
        try:
            peer.report = node.run()
        except (ControllerError, Exception) as exc:  # reported through peer.gone()
            peer.error = exc

    peer.thread = threading.Thread(target=work, name="controller", daemon=True)
    peer.thread.start()
    return peer
