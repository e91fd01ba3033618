"""Running a scenario: the plant, the bus, the controller as a separate program, the results.

`run_scenario` builds the FMUs and the co-simulation, opens the bus (by default it serves its own
loopback hub on 127.0.0.1, which the plant's bus hosts, and plant and controller speak its binary
records: `hil.run_bus`), starts the controller (a separate process by default, or a thread on
the virtual bus with `inprocess`: `hil.controller_peer`), serves SYNCs until the end, and writes
one folder: `signals.csv`, `can.log` (candump, simulation time), `controller.json` (what the
controller was told), `controller.log` (its stderr), plots (`*.png`), with `animate` the robot's
animation (`arm.gif`: hil.animation) and `summary.json`. If anything stops the run, the files
written so far stay complete and `summary.json` says why.

A run goes through its stages in `_run`, one function each: the folder's inputs
(`controller.json`, `scenario.toml`), the rig, the bus and the recorders, the plant against its
controller (in this thread over the direct bus, or against a thread or process over a bus), the
reports after the run (estimation, plots, animation) and the summary.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import json
import math
import multiprocessing
import re
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from threadpoolctl import threadpool_limits

from hil.animation import check_format
from hil.bus.direct import direct_pair
from hil.bus.hosted import HostedBus
from hil.controller_peer import ControllerPeer, start_controller
from hil.cosim.execution import OVERLAP_MIN_COST
from hil.devices import HEARTBEAT_PERIOD
from hil.environment import KERNEL_THREAD_SPIN, kernel_thread, two_cores
from hil.errors import HilError, ProtocolError, Terminated
from hil.plant import Plant, PlantStats, when
from hil.program import EXTERNAL, SOFTHIL, check_controller
from hil.recording import CanLogger, SignalRecorder, require_asammdf
from hil.results import RESULT_FILES, ResultsFolder, note, write_file
from hil.rig import robot_kind
from hil.run_bus import bus_specs, check_bus_opens, on_another_channel, open_spec
from hil.scenario import Scenario, can_log_problem, log_start
from hil.seam import ControllerNode, LockstepClock, RealtimeClock
from hil.summary import read_signals, realtime_failure, summarise
from rigbus.canbus import BusSpec
from rigbus.protocol import SYNC_ID, Protocol
from rigbus.robots import RobotConfig


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
    # the reports drawn after the run: the estimators' report, the plots and figures (not the
    # summary's scores, signals or CAN log, which are the run's own); False: `--no-reports`
    reports: bool = True
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


def controller_config(scenario: Scenario) -> RobotConfig:
    """What the controller is told, as the scenario's robot kind says."""
    return robot_kind(scenario.robot.kind).controller_config(scenario)  # type: ignore[no-any-return]


def run_scenario(scenario: Scenario, options: RunOptions) -> RunResult:
    """Run `scenario`; raises HilError after writing what it could if the run fails.

    The results folder is taken with a lock and must be empty (or hold only an earlier run's
    files, with `overwrite`); whatever stops the run, summary.json says why (status "failed",
    "interrupted" or "terminated", and "error") if the disk lets it be written."""
    scenario = _with_recording_options(scenario, options)
    _check_recording_options(scenario, options)
    _check_run_options(scenario, options)
    try:
        start = log_start(scenario)
    except ValueError as exc:
        raise HilError(f"--start: {exc}") from None
    scenario_text = _scenario_text(scenario)  # read before anything is written
    recording = scenario.recording
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
            _write_stopped(folder, summary, exc)
            raise


def _with_recording_options(scenario: Scenario, options: RunOptions) -> Scenario:
    """`scenario` with the [recording] keys the options override (--can-log, --start, --mf4)."""
    recording = scenario.recording
    recording = replace(
        recording,
        can_log=options.can_log or recording.can_log,
        start=recording.start if options.start is None else options.start,  # "" is refused
        mf4=recording.mf4 if options.mf4 is None else options.mf4,
    )
    return replace(scenario, recording=recording)


def _check_recording_options(scenario: Scenario, options: RunOptions) -> None:
    """Refuse, before anything runs, a CAN log this run cannot write: a bad --can-log name, or
    MF4 without asammdf."""
    recording = scenario.recording
    if options.can_log is not None:
        problem = can_log_problem(options.can_log)
        if problem is not None:
            raise HilError(f"--can-log: {problem}")
    source = scenario.source
    if recording.mf4:  # before anything runs: MF4 needs asammdf
        require_asammdf("--mf4" if options.mf4 else f"{source}: recording.mf4")
    if Path(recording.can_log).suffix == ".mf4":
        require_asammdf("--can-log" if options.can_log else f"{source}: recording.can_log")


def _check_run_options(scenario: Scenario, options: RunOptions) -> None:
    """Refuse, before anything runs, options this run cannot honour: an animation format this
    machine cannot write, a bus that does not open, a controller that is no program, --inprocess
    with another controller, a --wait out of range."""
    if options.animate is not None:  # before anything runs: a format this machine can write
        check_format(options.animate)
    check_bus_opens(scenario, options)
    check_controller(options.controller)
    if options.inprocess and options.controller != SOFTHIL:
        raise HilError(
            "--inprocess runs softhil's controller in this process; --controller "
            f"{options.controller} runs {'none' if options.controller == EXTERNAL else 'a program'}"
        )
    if options.wait is not None and not 0 < options.wait <= 86400:  # also NaN
        raise HilError(f"--wait: {options.wait:g} s; give 0 < SECONDS <= 86400 (a day)")


def _write_stopped(folder: ResultsFolder, summary: dict[str, Any], exc: BaseException) -> None:
    """summary.json of a run that `exc` stopped: its status and error, and for Ctrl-C or
    SIGTERM how far it got; a disk that refuses this one too is left to `exc` to tell."""
    summary["status"], summary["error"] = _stopped(exc)
    if summary["status"] != "failed" and "reached" in summary:  # Ctrl-C, SIGTERM
        summary["error"] += f" {when(summary['reached'])}"
    with contextlib.suppress(HilError):  # a full disk may refuse this one too
        _write_summary(folder, summary)


def _stopped(exc: BaseException) -> tuple[str, str]:
    """(status, error) of summary.json for what stopped a run."""
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted", "interrupted (SIGINT)"
    if isinstance(exc, Terminated):
        return "terminated", "terminated (SIGTERM)"
    return "failed", str(exc) or type(exc).__name__


@dataclass(frozen=True)
class _RunBus:
    """The bus of a run: the plant's end of it (and the controller's, on the direct bus), the
    specs plant and controller join, and where the run's own hub runs if it serves one."""

    plant: Any  # can.BusABC
    controller: Any  # the direct bus's other end; None off the direct bus
    plant_spec: BusSpec
    controller_spec: BusSpec
    hub: str | None
    direct: bool  # plant and controller in this thread, frames handed over synchronously


def _run(
    scenario: Scenario,
    options: RunOptions,
    folder: ResultsFolder,
    start: float,
    scenario_text: str,
    summary: dict[str, Any],
) -> RunResult:
    """The run in its taken `folder`, stage by stage; `summary` gathers what summary.json says
    (and, if the run stops, how far it got)."""
    recording = scenario.recording
    robot = robot_kind(scenario.robot.kind)
    config = robot.controller_config(scenario)
    _write_inputs(scenario, folder, config, scenario_text)
    protocol = Protocol()
    with ExitStack() as stack:
        rig = _build_rig(robot, scenario, options, stack)
        bus = _open_bus(scenario, options, stack)
        signals, can_log = _open_recorders(folder, rig, recording, start, stack)
        heartbeat_every = max(1, round(HEARTBEAT_PERIOD / scenario.timing.control_period))
        plant = Plant(scenario, bus.plant, rig, signals, can_log, protocol, heartbeat_every)
        progress = _progress_bar(scenario, options, stack)
        peer = ControllerPeer()
        try:
            if bus.direct:
                stats, report = _run_in_this_thread(plant, bus, config, protocol, options, progress)
            else:
                peer = start_controller(config, bus.controller_spec, options, folder, stack)
                stats, report = _run_against(plant, bus, peer, options, progress)
        except BaseException:
            summary["reached"] = plant.reached()  # how far the run got, in summary.json
            peer.stop()
            raise
        if recording.mf4:
            signals.close()
            signals.write_mf4(folder.claim("signals.mf4"))
    summary.update(
        summarise(scenario, folder.out / "signals.csv", stats, can_log, report, protocol)
    )
    _describe(summary, bus, stats, peer, rig, options)
    _reports(robot, rig, recording.can_log, options, folder, summary)
    return _finish(scenario, options, folder, summary, peer)


def _write_inputs(
    scenario: Scenario, folder: ResultsFolder, config: RobotConfig, scenario_text: str
) -> None:
    """controller.json (what the controller is told) and scenario.toml (the scenario as run),
    never over the input scenario of a rerun in its own folder."""
    write_file(folder.claim("controller.json"), config.to_json() + "\n")
    if not folder.kept("scenario.toml"):  # never the input scenario (a rerun in its folder)
        write_file(folder.claim("scenario.toml"), scenario_text)
    elif scenario_text.partition("\n")[2] != Path(scenario.source).read_text(encoding="utf-8"):
        note(
            f"{folder.out / 'scenario.toml'} is this run's input and is kept as it is; the run "
            f"used seed {scenario.seed} (summary.json)"
        )


def _build_rig(robot: Any, scenario: Scenario, options: RunOptions, stack: ExitStack) -> Any:
    """The robot's rig (its FMUs and co-simulation), closed with `stack`; an animation asked of
    a robot kind that has none is refused before the run, not after."""
    rig = robot.build(scenario)
    stack.callback(rig.close)
    if options.animate is not None and rig.animation is None:  # before the run, not after
        raise HilError(f"--animate: robot kind {scenario.robot.kind!r} has no animation")
    return rig


def _open_bus(scenario: Scenario, options: RunOptions, stack: ExitStack) -> _RunBus:
    """The run's bus, shut down with `stack`: the direct pair (--inprocess without --bus), or
    the bus `hil.run_bus` plans, with the run's own hub if it serves one."""
    if options.inprocess and not options.bus:
        plant_end, controller_end = direct_pair(f"softhil-{scenario.name}")
        stack.callback(controller_end.shutdown)
        spec = BusSpec("direct", "in-process")
        bus = _RunBus(plant_end, controller_end, spec, spec, None, direct=True)
    else:
        plant_spec, controller_spec, hosted, hub = bus_specs(scenario, options, stack)
        plant_bus = hosted if hosted is not None else open_spec(plant_spec)
        bus = _RunBus(plant_bus, None, plant_spec, controller_spec, hub, direct=False)
    stack.callback(bus.plant.shutdown)
    return bus


def _open_recorders(
    folder: ResultsFolder, rig: Any, recording: Any, start: float, stack: ExitStack
) -> tuple[SignalRecorder, CanLogger]:
    """The recorders of signals.csv and of the CAN log, closed with `stack`."""
    folder.claim("signals.units.csv")
    folder.claim("signals.parquet")  # the folder of the signals' blocks (hil.blocks)
    signals = SignalRecorder(folder.claim("signals.csv"), rig.signals)
    stack.callback(signals.close)
    can_log = CanLogger(folder.claim(recording.can_log), start=start)
    stack.callback(can_log.close)
    return signals, can_log


def _run_in_this_thread(
    plant: Plant,
    bus: _RunBus,
    config: RobotConfig,
    protocol: Protocol,
    options: RunOptions,
    progress: Callable[[int], None] | None,
) -> tuple[PlantStats, dict[str, Any]]:
    """softhil's controller and the plant in this thread over the direct bus: the plant's
    figures and the controller's report."""
    bus.plant.handler = plant.handle
    clock = RealtimeClock(config.control_period) if options.realtime else LockstepClock()
    node = ControllerNode(config, bus.controller, clock, protocol)
    overlap, min_cost = _kernel_overlap(options)
    # numpy's BLAS on one thread, as in a controller program (hil.program): on the
    # controller's small matrices more threads only spin, on the core that the FMUs'
    # worker thread steps on
    with threadpool_limits(limits=1, user_api="blas"):
        stats = plant.run_driven(node.run, progress, overlap, min_cost)
    return stats, asdict(node.report)


def _kernel_overlap(options: RunOptions) -> tuple[float | None, float]:
    """Whether the FMUs step on the kernel's worker thread while the controller runs: forced,
    off, or where it pays (two cores, not paced by the wall clock, a period that costs at least
    OVERLAP_MIN_COST). (the thread's spin, or None for in turn; the cost that decides)"""
    thread = kernel_thread()
    if thread is None:
        thread = two_cores() and not options.realtime
        min_cost = OVERLAP_MIN_COST
    else:
        min_cost = 0.0
    return (KERNEL_THREAD_SPIN if thread else None), min_cost


def _run_against(
    plant: Plant,
    bus: _RunBus,
    peer: ControllerPeer,
    options: RunOptions,
    progress: Callable[[int], None] | None,
) -> tuple[PlantStats, dict[str, Any]]:
    """The plant against a controller on the bus (a thread, a program, or one started by
    hand) until the final SYNC: the plant's figures and the controller's report."""
    if isinstance(bus.plant, HostedBus):  # who sends the SYNCs: see ControllerPeer.gone
        peer.hub = bus.plant
        bus.plant.watch(SYNC_ID)
    try:
        stats = plant.run(peer.gone, progress, startup_timeout=options.wait)
    except ProtocolError as exc:
        raise on_another_channel(exc, bus.plant, plant.cycle) from None
    return stats, peer.finish()


def _describe(
    summary: dict[str, Any],
    bus: _RunBus,
    stats: PlantStats,
    peer: ControllerPeer,
    rig: Any,
    options: RunOptions,
) -> None:
    """summary.json's account of how the run ran: its bus and hub, where the controller and
    the FMUs ran, the controller's warnings and the rig's parameters."""
    summary["bus"] = str(bus.plant_spec)
    summary["hub"] = bus.hub
    # in one thread with the controller: the periods the FMUs stepped on the kernel's thread
    summary["periods_on_kernel_thread"] = stats.periods_on_thread if bus.direct else None
    if bus.direct:
        summary["controller_process"] = "this thread"
    elif options.inprocess:
        summary["controller_process"] = "thread"
    else:
        summary["controller_process"] = "external" if options.controller == EXTERNAL else "process"
    summary["controller_program"] = options.controller  # softhil, external or a command line
    summary["warnings"].extend(peer.warnings)
    summary["parameters"] = {name: dict(values) for name, values in rig.parameters.items()}


def _reports(
    robot: Any,
    rig: Any,
    can_log: str,
    options: RunOptions,
    folder: ResultsFolder,
    summary: dict[str, Any],
) -> None:
    """The reports drawn from the recorded run: the estimators' report (the planar arm's, from
    a CAN log with directions; in a child process with `parallel_report`), the rig's plots and
    figures (none of these with `reports` False), the animation asked for."""
    out = folder.out
    with ExitStack() as post:
        estimation = None
        if (
            options.reports
            and can_log.endswith((".log", ".blf", ".asc", ".trc"))
            and getattr(robot, "estimation_report", True)
        ):  # the curvature estimators' report: the planar arm's
            folder.claim("estimation.png")
            summary["estimation"] = None  # its place in summary.json; filled below
            estimation = post.enter_context(
                _estimation_report(out, options.parallel_report, can_log)
            )
        animation = rig.animation if options.animate is not None else None
        if options.reports or animation is not None:
            recorded = read_signals(out / "signals.csv")
            if options.reports:
                from hil.plots import plot_run

                for spec in rig.plots:
                    folder.claim(f"{spec.name}.png")
                plot_run(recorded, rig.plots, out)
                for name, draw in rig.figures:
                    draw(recorded, folder.claim(f"{name}.png"))
            if animation is not None:
                name, animate = animation
                summary["animation"] = f"{name}.{options.animate}"
                animate(recorded, folder.claim(summary["animation"]), options.animate)
        if estimation is not None:
            scores, error = estimation()
            summary["estimation"] = scores if error is None else {"error": error}
            if error is not None:  # a log with intruders' frames: report it, keep the run
                summary["warnings"].append(f"no estimation report: {error}")


def _finish(
    scenario: Scenario,
    options: RunOptions,
    folder: ResultsFolder,
    summary: dict[str, Any],
    peer: ControllerPeer,
) -> RunResult:
    """The verdict: a real-time run too late, or a program that failed after the final SYNC,
    fails the run (summary.json is then written by run_scenario); else summary.json."""
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
    return RunResult(folder.out, summary)


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
