"""Running a scenario: the plant, the bus, the controller as a separate program, the results.

`run_scenario` builds the FMUs and the co-simulation, opens the bus (by default it serves its own
loopback hub on 127.0.0.1, in a child process, and plant and controller speak its binary
records), starts the controller (a separate process by default, or a thread on
the virtual bus with `inprocess`), serves SYNCs until the end, and writes one folder:
`signals.csv`, `can.log` (candump, simulation time), `controller.json` (what the controller was
told), `controller.log` (its stderr), plots (`*.png`), with `animate` the robot's animation
(`arm.gif`: hil.animation) and `summary.json`. If anything stops the run, the files written so
far stay complete and `summary.json` says why.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import json
import math
import multiprocessing
import os
import re
import shlex
import subprocess
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from threadpoolctl import threadpool_limits

from controllers.node import (
    ControllerConfig,
    ControllerError,
    ControllerNode,
    LockstepClock,
    RealtimeClock,
)
from hil.animation import check_format
from hil.bus.direct import direct_pair
from hil.bus.hosted import HostedBus
from hil.bus.loopback import HubProcess, LoopbackHub
from hil.devices import HEARTBEAT_PERIOD
from hil.environment import KERNEL_THREAD_SPIN, kernel_thread, two_cores
from hil.errors import BusError, HilError, ProtocolError, Terminated
from hil.plant import OVERLAP_MIN_COST, STARTUP_TIMEOUT, Plant, when
from hil.program import (
    EXTERNAL,
    SOFTHIL,
    USER_LINGER,
    check_controller,
    group_alive,
    last_words,
    placeholder_values,
    start,
)
from hil.program import stop as stop_program
from hil.recording import CanLogger, SignalRecorder, require_asammdf
from hil.results import RESULT_FILES, ResultsFolder, note, write_file
from hil.robots import robot_kind
from hil.scenario import Scenario, can_log_problem, log_start
from hil.summary import read_signals, realtime_failure, summarise
from rigbus.binary import busy_poll_seconds
from rigbus.canbus import HUB_KINDS, BusOpenError, BusSpec, open_bus
from rigbus.protocol import SYNC_ID, Protocol


@dataclass(frozen=True)
class RunOptions:
    out: Path
    bus: str | None = None  # a bus spec overriding the scenario's
    inprocess: bool = False
    realtime: bool = False
    progress: bool = True
    can_log: str | None = None  # file name overriding [recording] can_log (suffix: format)
    start: str | None = None  # overriding [recording] start: ISO 8601 or "now"
    mf4: bool | None = None  # overriding [recording] mf4
    overwrite: bool = False  # replace the files an earlier run wrote in `out` (never others)
    animate: str | None = None  # write the robot's animation in this format ("gif", "mp4")
    # score the estimators (estimation.png, summary "estimation") in a child process while this
    # one draws the plots: `hil run` does, on a machine with a core to spare (not in batches,
    # whose trials already take the cores)
    parallel_report: bool = False
    # the controller program (hil.program): "softhil" (ours), "external" (none: one started by
    # hand on the run's bus), or a user's command line with placeholders
    controller: str = SOFTHIL
    # [s] for the controller's first SYNC (None: STARTUP_TIMEOUT, or the scenario's controller
    # timeout if longer)
    wait: float | None = None


@dataclass(frozen=True)
class RunResult:
    out: Path
    summary: dict[str, Any]


def controller_config(scenario: Scenario) -> ControllerConfig:
    """What the controller is told, as the scenario's robot kind says."""
    return robot_kind(scenario.robot.kind).controller_config(scenario)  # type: ignore[no-any-return]


def run_scenario(scenario: Scenario, options: RunOptions) -> RunResult:
    """Run `scenario`; raises HilError after writing what it could if the run fails.

    The results folder is taken with a lock and must be empty (or hold only an earlier run's
    files, with `overwrite`); whatever stops the run, summary.json says why (status "failed",
    "interrupted" or "terminated", and "error") if the disk lets it be written."""
    recording = scenario.recording
    recording = replace(
        recording,
        can_log=options.can_log or recording.can_log,
        start=recording.start if options.start is None else options.start,  # "" is refused
        mf4=recording.mf4 if options.mf4 is None else options.mf4,
    )
    scenario = replace(scenario, recording=recording)
    if options.can_log is not None:
        problem = can_log_problem(options.can_log)
        if problem is not None:
            raise HilError(f"--can-log: {problem}")
    source = scenario.source
    if recording.mf4:  # before anything runs: MF4 needs asammdf
        require_asammdf("--mf4" if options.mf4 else f"{source}: recording.mf4")
    if Path(recording.can_log).suffix == ".mf4":
        require_asammdf("--can-log" if options.can_log else f"{source}: recording.can_log")
    if options.animate is not None:  # before anything runs: a format this machine can write
        check_format(options.animate)
    _check_bus_opens(scenario, options)
    check_controller(options.controller)
    if options.inprocess and options.controller != SOFTHIL:
        raise HilError(
            "--inprocess runs softhil's controller in this process; --controller "
            f"{options.controller} runs {'none' if options.controller == EXTERNAL else 'a program'}"
        )
    if options.wait is not None and not 0 < options.wait <= 86400:  # also NaN
        raise HilError(f"--wait: {options.wait:g} s; give 0 < SECONDS <= 86400 (a day)")
    try:
        start = log_start(scenario)
    except ValueError as exc:
        raise HilError(f"--start: {exc}") from None
    scenario_text = _scenario_text(scenario)  # read before anything is written
    planned = (*RESULT_FILES, recording.can_log)
    keep = [Path(scenario.source)] if Path(scenario.source).is_file() else []
    with ResultsFolder(options.out, planned, options.overwrite, keep) as folder:
        for text in folder.notes:
            note(text)
        summary: dict[str, Any] = {
            "scenario": scenario.name,
            "seed": scenario.seed,
            "status": "failed",
            "can_log": recording.can_log,  # where `hil estimate` finds it, whatever stops the run
        }
        try:
            return _run(scenario, options, folder, start, scenario_text, summary)
        except BaseException as exc:
            summary["status"], summary["error"] = _stopped(exc)
            if summary["status"] != "failed" and "reached" in summary:  # Ctrl-C, SIGTERM
                summary["error"] += f" {when(summary['reached'])}"
            with contextlib.suppress(HilError):  # a full disk may refuse this one too
                _write_summary(folder, summary)
            raise


def _on_another_channel(exc: ProtocolError, bus: object, cycle: int) -> ProtocolError:
    """A controller that never sent SYNC(0) to the hub the plant hosts may have joined another
    channel of it: `exc` saying which, if one did."""
    if not isinstance(bus, HostedBus) or cycle >= 0:
        return exc
    others = bus.elsewhere()
    if not others:
        return exc
    names = ", ".join(repr(name) for name in others)
    return ProtocolError(
        f"{exc}; a client joined the hub's channel {names}, not this run's "
        f"{bus.channel_name!r} (the channel of its bus spec)"
    )


def _stopped(exc: BaseException) -> tuple[str, str]:
    """(status, error) of summary.json for what stopped a run."""
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted", "interrupted (SIGINT)"
    if isinstance(exc, Terminated):
        return "terminated", "terminated (SIGTERM)"
    return "failed", str(exc) or type(exc).__name__


def _run(
    scenario: Scenario,
    options: RunOptions,
    folder: ResultsFolder,
    start: float,
    scenario_text: str,
    summary: dict[str, Any],
) -> RunResult:
    out = folder.out
    recording = scenario.recording
    robot = robot_kind(scenario.robot.kind)
    config = robot.controller_config(scenario)
    write_file(folder.claim("controller.json"), config.to_json() + "\n")
    if not folder.kept("scenario.toml"):  # never the input scenario (a rerun in its folder)
        write_file(folder.claim("scenario.toml"), scenario_text)
    elif scenario_text.partition("\n")[2] != Path(scenario.source).read_text(encoding="utf-8"):
        note(
            f"{out / 'scenario.toml'} is this run's input and is kept as it is; the run used "
            f"seed {scenario.seed} (summary.json)"
        )
    protocol = Protocol()
    with ExitStack() as stack:
        rig = robot.build(scenario)
        stack.callback(rig.close)
        if options.animate is not None and rig.animation is None:  # before the run, not after
            raise HilError(f"--animate: robot kind {scenario.robot.kind!r} has no animation")
        direct = options.inprocess and not options.bus
        hub: str | None = None  # where hil run's own hub runs, if it serves one
        if direct:  # plant and controller in this thread, frames handed over synchronously
            plant_bus, controller_bus = direct_pair(f"softhil-{scenario.name}")
            stack.callback(controller_bus.shutdown)
            plant_spec = controller_spec = BusSpec("direct", "in-process")
        else:
            plant_spec, controller_spec, hosted, hub = _bus_specs(scenario, options, stack)
            plant_bus = hosted if hosted is not None else _open(plant_spec)
        stack.callback(plant_bus.shutdown)
        folder.claim("signals.units.csv")
        folder.claim("signals.parquet")  # the folder of the signals' blocks (hil.blocks)
        signals = SignalRecorder(folder.claim("signals.csv"), rig.signals)
        stack.callback(signals.close)
        can_log = CanLogger(folder.claim(recording.can_log), start=start)
        stack.callback(can_log.close)
        heartbeat_every = max(1, round(HEARTBEAT_PERIOD / scenario.timing.control_period))
        plant = Plant(scenario, plant_bus, rig, signals, can_log, protocol, heartbeat_every)
        progress = _progress_bar(scenario, options, stack)
        peer = _Peer()
        try:
            if direct:
                plant_bus.handler = plant.handle
                clock = (
                    RealtimeClock(config.control_period) if options.realtime else LockstepClock()
                )
                node = ControllerNode(config, controller_bus, clock, protocol)
                # the FMUs on the kernel's worker thread: forced, off, or where it pays
                thread = kernel_thread()
                if thread is None:
                    thread = two_cores() and not options.realtime
                    min_cost = OVERLAP_MIN_COST
                else:
                    min_cost = 0.0
                overlap = KERNEL_THREAD_SPIN if thread else None
                # numpy's BLAS on one thread, as in a controller program (hil.program): on the
                # controller's small matrices more threads only spin, on the core that the FMUs'
                # worker thread steps on
                with threadpool_limits(limits=1, user_api="blas"):
                    stats = plant.run_driven(node.run, progress, overlap, min_cost)
                report = asdict(node.report)
            else:
                peer = _start_controller(config, controller_spec, options, folder, stack)
                if isinstance(plant_bus, HostedBus):  # who sends the SYNCs: see _Peer.gone
                    peer.hub = plant_bus
                    plant_bus.watch(SYNC_ID)
                try:
                    stats = plant.run(peer.gone, progress, startup_timeout=options.wait)
                except ProtocolError as exc:
                    raise _on_another_channel(exc, plant_bus, plant.cycle) from None
                report = peer.finish()
        except BaseException:
            summary["reached"] = plant.reached()  # how far the run got, in summary.json
            peer.stop()
            raise
        if recording.mf4:
            signals.close()
            signals.write_mf4(folder.claim("signals.mf4"))
    summary.update(summarise(scenario, out / "signals.csv", stats, can_log, report, protocol))
    summary["bus"] = str(plant_spec)
    summary["hub"] = hub
    # in one thread with the controller: the periods the FMUs stepped on the kernel's thread
    summary["periods_on_kernel_thread"] = stats.periods_on_thread if direct else None
    if direct:
        summary["controller_process"] = "this thread"
    elif options.inprocess:
        summary["controller_process"] = "thread"
    else:
        summary["controller_process"] = "external" if options.controller == EXTERNAL else "process"
    summary["controller_program"] = options.controller  # softhil, external or a command line
    summary["warnings"].extend(peer.warnings)
    summary["parameters"] = {name: dict(values) for name, values in rig.parameters.items()}
    with ExitStack() as post:
        estimation = None
        if recording.can_log.endswith((".log", ".blf", ".asc", ".trc")) and getattr(
            robot, "estimation_report", True
        ):  # the curvature estimators' report: the planar arm's
            folder.claim("estimation.png")
            summary["estimation"] = None  # its place in summary.json; filled below
            estimation = post.enter_context(
                _estimation_report(out, options.parallel_report, recording.can_log)
            )
        from hil.plots import plot_run

        for spec in rig.plots:
            folder.claim(f"{spec.name}.png")
        recorded = read_signals(out / "signals.csv")
        plot_run(recorded, rig.plots, out)
        for name, draw in rig.figures:
            draw(recorded, folder.claim(f"{name}.png"))
        if options.animate is not None and rig.animation is not None:
            name, animate = rig.animation
            summary["animation"] = f"{name}.{options.animate}"
            animate(recorded, folder.claim(summary["animation"]), options.animate)
        if estimation is not None:
            scores, error = estimation()
            summary["estimation"] = scores if error is None else {"error": error}
            if error is not None:  # a log with intruders' frames: report it, keep the run
                summary["warnings"].append(f"no estimation report: {error}")
    summary["realtime"] = options.realtime
    # the pace is checked by the controller's own figures (the one that paces the SYNCs): on a
    # run that was not real-time, a report's figures are not a failure
    failure = realtime_failure(scenario, summary["controller"]) if options.realtime else None
    if options.realtime and not summary["controller"].get("realtime"):
        summary["warnings"].append(
            "--realtime: the controller reported no SYNC lateness (report keys realtime, "
            "overruns, max_lateness, mean_lateness), so the real-time pace is not verified"
        )
    if failure is not None:
        summary["warnings"].append(failure)
        raise HilError(failure)
    if peer.failure is not None:  # every cycle recorded and scored; the program still failed
        raise HilError(peer.failure)
    _write_summary(folder, summary)
    return RunResult(out, summary)


def _score_estimators(
    out: Path, can_log: str | None = None
) -> tuple[dict[str, Any] | None, str | None]:
    """The estimation report of the run in `out` (its CAN log `can_log`, by default the one
    found there), or why there is none."""
    from hil.estimation import estimation_report

    try:
        return estimation_report(out, log=None if can_log is None else out / can_log), None
    except HilError as exc:
        return None, str(exc)


@contextlib.contextmanager
def _estimation_report(
    out: Path, parallel: bool, can_log: str | None = None
) -> Iterator[Callable[[], tuple[dict[str, Any] | None, str | None]]]:
    """`_score_estimators(out, can_log)`, started in a forked child process if `parallel` (and the
    platform forks, and this process may have children: a daemon may not), else when asked
    for; yields the call that returns it."""
    if (
        parallel
        and "fork" in multiprocessing.get_all_start_methods()
        and not multiprocessing.current_process().daemon
    ):
        with concurrent.futures.ProcessPoolExecutor(
            1, mp_context=multiprocessing.get_context("fork")
        ) as pool:
            future = pool.submit(_score_estimators, out, can_log)
            yield future.result
        return
    yield lambda: _score_estimators(out, can_log)


def _scenario_text(scenario: Scenario) -> str:
    """The scenario file as run: its text, with the seed that was used."""
    source = Path(scenario.source)
    text = source.read_text(encoding="utf-8") if source.is_file() else ""
    text, found = re.subn(r"(?m)^seed\s*=.*$", f"seed = {scenario.seed}", text, count=1)
    header = f"# scenario {scenario.source}, run with seed {scenario.seed}\n"
    return header + (text if found else f"seed = {scenario.seed}\n" + text)


def _write_summary(folder: ResultsFolder, summary: dict[str, Any]) -> None:
    """summary.json: strict JSON, a metric that does not exist (never settled, no step) is null."""
    text = json.dumps(_finite(summary), indent=2, sort_keys=True, allow_nan=False)
    write_file(folder.claim("summary.json"), text + "\n")


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def _open(spec: BusSpec):  # noqa: ANN202 - can.BusABC
    try:
        return open_bus(spec)
    except BusOpenError as exc:
        raise BusError(str(exc)) from exc


def bus_option(options: RunOptions) -> BusSpec | None:
    """--bus as a spec (None: not given, or --inprocess's virtual bus); HilError for a spec
    that cannot be, checked before the results folder is made (a misspelt interface is not a
    failed run)."""
    if not options.bus:
        return None
    if options.inprocess:
        if not options.bus.startswith("virtual"):
            raise HilError(f"--inprocess runs on the virtual bus, not {options.bus}")
        return None
    try:
        spec = BusSpec.parse(options.bus)
    except ValueError as exc:
        raise HilError(str(exc)) from exc
    if spec.kind == "virtual":
        raise HilError("a virtual bus only joins one process: use --inprocess, or --bus loopback")
    return spec


def _check_bus_opens(scenario: Scenario, options: RunOptions) -> None:
    """Open the bus the run is to join (not a hub of its own) and close it again, before the
    results folder is made: a bus that cannot be opened is one line, not a failed run whose
    folder then refuses the retry its message suggests."""
    spec = bus_option(options)
    if options.inprocess:
        return
    if spec is None:
        b = scenario.bus
        if b.kind == "virtual" or (b.kind in HUB_KINDS and b.port == 0):
            return  # refused by _bus_specs; or the run's own hub
        spec = BusSpec(b.kind, b.channel, b.host, b.port)
    _open(spec).shutdown()


def _bus_specs(
    scenario: Scenario, options: RunOptions, stack: ExitStack
) -> tuple[BusSpec, BusSpec, HostedBus | None, str | None]:
    """(plant's spec, controller's spec, the plant's bus if the plant hosts the hub, where
    the run's own hub runs if it has one). A loopback bus without a port gets its own hub."""
    given = bus_option(options)
    if options.inprocess:
        channel = f"softhil-{uuid.uuid4().hex[:8]}"  # a private channel per run
        if options.bus and options.bus.startswith("virtual:"):
            channel = options.bus.partition(":")[2]  # a channel named by the user
        spec = BusSpec("virtual", channel)
        return spec, spec, None, None
    if given is not None:
        spec = given
    else:
        b = scenario.bus
        spec = BusSpec(b.kind, b.channel, b.host, b.port or 0)
        if spec.kind == "virtual":
            raise HilError(
                "a virtual bus only joins one process: use --inprocess, or --bus loopback"
            )
    if spec.kind in HUB_KINDS and (options.bus is None and scenario.bus.port == 0):
        # our own hub: plant and controller speak its binary records (the ASCII socketcand
        # protocol stays open on the same port for tools); the hub runs where SOFTHIL_HUB says
        mode = os.environ.get("SOFTHIL_HUB", "plant")
        busy_poll = _busy_poll(mode, options)
        port, hosted = _serve_hub(spec.host, spec.channel, mode, busy_poll, stack)
        extra = (("busy_poll", f"{busy_poll:g}"),) if busy_poll else ()
        spec = replace(spec, kind="softhil", port=port, options=extra)
        return spec, spec, hosted, mode
    return spec, spec, None, None


HUB_MODES = ("plant", "process", "thread")
# [s] how long the plant and the controller poll the run's own hub before they sleep, when the
# plant hosts it: each waits for the other once a SYNC, mostly for less than this, and waking
# a sleeping process costs hundreds of microseconds on a virtual machine (6 segments across
# processes, 2 cores: 3.8-5.0x real time -> 6.1-9.3x; 0.3 ms helped one run in three). Each
# poll yields the core to any process that needs it: two such runs at once on 2 cores ran at
# 1.6x each polling without yielding, 3.9-5.9x yielding, 4.7-5.1x sleeping at once
BUSY_POLL = 0.002


def _busy_poll(mode: str, options: RunOptions) -> float:
    """The busy-poll budget [s] of the run's own hub clients: SOFTHIL_BUSY_POLL if set, else
    BUSY_POLL when the plant hosts the hub, the run is not paced by the wall clock, and this
    process may use two cores or more (the two processes then poll on cores of their own);
    else 0 (a thread or child-process hub shares the cores with both)."""
    text = os.environ.get("SOFTHIL_BUSY_POLL")
    if text is not None:
        try:
            return busy_poll_seconds(text)
        except ValueError as exc:
            raise HilError(f"SOFTHIL_BUSY_POLL: {exc}") from None
    if mode != "plant" or options.realtime:
        return 0.0
    return BUSY_POLL if two_cores() else 0.0


def _serve_hub(
    host: str, channel: str, mode: str, busy_poll: float, stack: ExitStack
) -> tuple[int, HostedBus | None]:
    """Start a hub for this run: its port, and the plant's bus if the plant hosts it.
    ``plant`` (the default): the plant's own bus is the hub (`hil.bus.hosted`), one hop and
    one process fewer each way; ``process``: a child process; ``thread``: a thread of this
    process (both measured against it in bench/bench_run.py)."""
    if mode == "plant":
        bus = HostedBus(channel, host, busy_poll=busy_poll)
        stack.callback(bus.shutdown)
        return bus.port, bus
    if mode == "process":
        child = HubProcess(host)
        stack.callback(child.stop)
        return child.port, None
    if mode == "thread":
        hub = LoopbackHub(host).start()
        stack.callback(hub.stop)
        return hub.port, None
    raise HilError(f"SOFTHIL_HUB={mode!r}: must be one of {', '.join(HUB_MODES)}")


class _Peer:
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
        if now - self._closed_since < CLOSED_GRACE:
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
            timeout = USER_LINGER if self.user else FINISH_TIMEOUT
            try:
                code = self.process.wait(timeout=timeout)
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
                code = 0
            else:
                if group_alive(self.process):  # its own process is gone, children it left not
                    self.stop()
                    self.warnings.append(
                        "the controller program left processes running after it exited; the "
                        "run stopped them"
                    )
            if self.log is not None:
                self.log.with_name("controller.pid").unlink(missing_ok=True)
            if code != 0:  # after the final SYNC: the run is whole, scored, and then failed
                self.failure = (
                    f"the controller failed with code {code} after the final SYNC"
                    f"{self._last_words()}"
                )
            report_path = self.log.with_name("controller_report.json") if self.log else None
            if report_path and report_path.is_file() and report_path.stat().st_size:
                size = report_path.stat().st_size
                try:
                    if self.user and size > MAX_REPORT_BYTES:
                        raise ValueError(f"{size} bytes, more than {MAX_REPORT_BYTES}")
                    report = json.loads(report_path.read_text(errors="replace"))
                    if self.user and _depth(report) > MAX_REPORT_DEPTH:
                        raise ValueError(f"nested deeper than {MAX_REPORT_DEPTH} levels")
                except (ValueError, RecursionError) as exc:
                    report = exc
                if isinstance(report, dict):
                    return _checked_report(report, report_path) if self.user else report
                if not self.user:
                    raise HilError(f"{report_path}: not the controller's report: {report}")
                note(f"{report_path}: not a JSON object ({report}); the summary leaves it out")
            return {}
        if self.thread is not None:
            self.thread.join(timeout=30)
            if self.thread.is_alive():
                raise HilError("the controller thread did not finish within 30 s of the last SYNC")
            if self.error is not None:
                raise HilError(f"the controller failed: {self.error}")
            return asdict(self.report) if self.report is not None else {}
        return {}


MAX_REPORT_BYTES = 1 << 20  # a user program's report in summary.json: at most 1 MiB
MAX_REPORT_DEPTH = 32  # and at most this deep (json and the summary's writer recurse)


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


FINISH_TIMEOUT = 30.0  # [s] softhil's controller has after the final SYNC to exit
# [s] the connection that sent the SYNCs may stay closed before the controller is taken for
# gone: a program's exit shows first (with its code), a controller that reconnects resumes
CLOSED_GRACE = 1.0


def _clock(config: ControllerConfig, options: RunOptions) -> LockstepClock | RealtimeClock:
    return RealtimeClock(config.control_period) if options.realtime else LockstepClock()


def _start_controller(
    config: ControllerConfig,
    spec: BusSpec,
    options: RunOptions,
    folder: ResultsFolder,
    stack: ExitStack,
) -> _Peer:
    peer = _Peer()
    if options.inprocess:
        bus = _open(spec)
        stack.callback(bus.shutdown)
        clock = RealtimeClock(config.control_period) if options.realtime else LockstepClock()
        node = ControllerNode(config, bus, clock)

        def work() -> None:
            try:
                peer.report = node.run()
            except (ControllerError, Exception) as exc:  # reported through peer.gone()
                peer.error = exc

        peer.thread = threading.Thread(target=work, name="controller", daemon=True)
        peer.thread.start()
        return peer
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


def _progress_bar(
    scenario: Scenario, options: RunOptions, stack: ExitStack
) -> Callable[[int], None] | None:
    if not options.progress:
        return None
    from tqdm import tqdm

    bar = tqdm(
        total=scenario.cycles,
        unit="SYNC",
        desc=scenario.name,
        disable=None,
        leave=False,
        mininterval=0.2,
    )
    stack.callback(bar.close)
    last = [0]

    def update(cycle: int) -> None:
        if cycle - last[0] >= 10 or cycle == scenario.cycles:
            bar.update(cycle - last[0])
            last[0] = cycle

    return update
