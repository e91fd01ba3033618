"""`hil run`: run a scenario and write its results folder."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

from hil.animation import FORMATS
from hil.errors import HilError
from hil.run import RunOptions, run_scenario
from hil.scenario import load_scenario, resolve_scenario


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli.parsers import example_parser

    parser = example_parser(
        commands,
        "run",
        "run a scenario: the plant here, the controller as a separate program, over CAN",
        "  hil run                                  the default scenario\n"
        "  hil run planar-path                      a built-in scenario (`hil scenarios`)\n"
        "  hil run my.toml --out runs/try1 --seed 7\n"
        "  hil run --inprocess                      controller in this process, virtual bus\n"
        "  hil run --realtime                       SYNC paced by the wall clock\n"
        "  hil run --bus loopback:127.0.0.1:29536   join a hub started by `hil bus serve`\n"
        "  hil run planar-pipe-1 --animate          also arm.gif: the run seen from above\n"
        "  hil run --controller 'python my_ctrl.py --config {config} --bus {bus}'\n"
        "                                           your controller program against the rig\n"
        "  hil run --controller external --bus loopback:127.0.0.1:29536\n"
        "                                           no program: wait for one started by hand\n",
    )
    parser.add_argument(
        "scenario",
        nargs="?",
        metavar="NAME|FILE",
        help="a scenario TOML file, or the name of a built-in scenario (`hil scenarios`); "
        "default: the built-in default",
    )
    parser.add_argument(
        "--out",
        help="results folder, new or empty (default: runs/NAME-SEED); softhil never replaces "
        "files it did not write",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="reuse a results folder: replace the files an earlier run wrote there (listed in "
        "its .softhil-manifest), never other files or the input scenario",
    )
    parser.add_argument("--bus", help="bus spec: loopback[:HOST:PORT], socketcan:IFACE, virtual")
    parser.add_argument(
        "--inprocess",
        action="store_true",
        help="run softhil's controller in this thread over a direct in-process bus (with "
        "--bus virtual[:CHANNEL]: in a thread, over python-can's virtual bus)",
    )
    parser.add_argument(
        "--controller",
        default="softhil",
        metavar="softhil|external|COMMAND",
        help="the controller program: softhil's own; none (external: one you start on the "
        "run's bus, which sends SYNC(0) within --wait); or your command line, split as a shell "
        "would, with {config} {report} {bus} {interface} {channel} {host} {port} {realtime} "
        "{dbc} replaced (also as SOFTHIL_CONFIG, ... in its environment; README: Your controller)",
    )
    parser.add_argument(
        "--wait",
        type=float,
        metavar="SECONDS",
        help="how long the run waits for the controller's first SYNC (default: 60, or the "
        "scenario's controller.timeout if longer); with --controller external, time to start "
        "yours",
    )
    parser.add_argument("--realtime", action="store_true", help="pace SYNC on the wall clock")
    parser.add_argument("--seed", type=int, help="override the scenario's seed")
    parser.add_argument(
        "--can-log",
        metavar="FILE",
        help="CAN log file name in the results folder; its suffix picks the format: .log "
        "(candump), .asc, .blf, .trc, .csv, .mf4 (needs asammdf) (default: [recording] can_log, "
        "can.log)",
    )
    parser.add_argument(
        "--start",
        metavar="INSTANT",
        help="CAN log start: ISO 8601 (2015-06-01T00:00:00Z) or 'now' (default: [recording] "
        "start, fixed so reruns are byte-identical)",
    )
    parser.add_argument(
        "--mf4", action="store_true", default=None, help="also write signals.mf4 (needs asammdf)"
    )
    parser.add_argument(
        "--animate",
        nargs="?",
        const="gif",
        metavar="gif|mp4",
        help="also write the robot's animation of the run (arm.gif; mp4 needs ffmpeg on PATH); "
        "a bare --animate writes a GIF",
    )
    parser.add_argument(
        "--no-reports",
        action="store_true",
        help="skip the reports drawn after the run (the plots, figures and the estimators' "
        "report): the CAN log, signals and summary are written as always",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    if args.out is not None and not args.out.strip():
        raise HilError("--out: an empty folder name; name the results folder")
    if args.animate is not None and args.animate not in FORMATS and args.scenario is None:
        # `hil run --animate planar-path` took the scenario for the format
        raise HilError(
            f"--animate: unknown format {args.animate!r} (known: {', '.join(FORMATS)}); a "
            "scenario goes before it: hil run NAME --animate"
        )
    path = None if args.scenario is None else resolve_scenario(args.scenario)
    scenario = load_scenario(path, seed=args.seed)
    out = Path(args.out) if args.out else Path("runs") / f"{scenario.name}-{scenario.seed}"
    result = run_scenario(
        scenario,
        RunOptions(
            out=out,
            bus=args.bus,
            inprocess=args.inprocess,
            realtime=args.realtime,
            progress=not args.no_progress,
            can_log=args.can_log,
            start=args.start,
            mf4=args.mf4,
            overwrite=args.overwrite,
            animate=args.animate,
            reports=not args.no_reports,
            parallel_report=(os.cpu_count() or 1) > 1,
            controller=args.controller,
            wait=args.wait,
        ),
    )
    s = result.summary
    print(
        f"{scenario.name}: {scenario.duration:g} s simulated in {s['wall_time']:.2f} s "
        f"(real-time factor {s['real_time_factor']:.1f}) over {s['bus']}"
    )
    print(f"  {task_line(s)}")
    f = s["frames"]
    print(
        f"  bus load {100 * s['bus_load']:.1f} % at {s['bitrate'] / 1000:g} kbit/s; frames sent "
        f"{f['sent']}, received {f['received']}, missed {f['missed']}"
    )
    controller = s.get("controller", {})
    if controller.get("realtime"):
        print(
            f"  real time: SYNC lateness max {1e3 * controller['max_lateness']:.2f} ms, "
            f"mean {1e3 * controller['mean_lateness']:.2f} ms, overruns {controller['overruns']}"
        )
    for warning in s["warnings"]:
        print(f"  warning: {warning}", file=sys.stderr)
    drawn = "" if args.no_reports else ", *.png"
    animation = f", {s['animation']}" if "animation" in s else ""
    print(
        f"  results in {result.out}/ (signals.csv, {s['can_log']}{drawn}{animation}, summary.json)"
    )
    return 0


def _shown(value: object, scale: float, spec: str, unit: str) -> str:
    """A metric for the terminal: n/a where the task has none, 'never' where it never settled."""
    if not isinstance(value, int | float):
        return "n/a"
    if math.isinf(value):
        return "never"
    return f"{scale * value:{spec}}{unit}"


def task_line(s: dict[str, object]) -> str:
    """The task's headline metrics for the terminal, by what the summary holds."""
    if "tip_error_mean" in s:
        return (
            f"tip error mean {_shown(s['tip_error_mean'], 1e3, '.2f', ' mm')}, std "
            f"{_shown(s['tip_error_std'], 1e3, '.2f', ' mm')}, max "
            f"{_shown(s['tip_error_max'], 1e3, '.2f', ' mm')}; settled {s['targets_settled']} of "
            f"{s['targets']} targets, time to settle {_shown(s['time_to_settle'], 1, '.2f', ' s')}"
        )
    if "shape_error_mean" in s:  # the spatial arm's shape fitting
        return (
            f"shape error mean {_shown(s['shape_error_mean'], 1e3, '.2f', ' mm')}, max "
            f"{_shown(s['shape_error_max'], 1e3, '.2f', ' mm')} over {s['curve_points']} "
            f"points of the curve; tip {_shown(s['tip_error_final'], 1e3, '.2f', ' mm')} "
            "from its end"
        )
    if "bend_error_mean" in s:  # the spatial arm's configuration control
        return (
            f"bend error mean {_shown(s['bend_error_mean'], 1, '.4f', ' rad')}, max "
            f"{_shown(s['bend_error_max'], 1, '.4f', ' rad')} over {s['steps_pursued']} of "
            f"{s['steps']} steps"
        )
    if "place_error" in s:  # grasp-and-place
        return (
            f"{'success' if s['success'] else 'failure'}: object "
            f"{_shown(s['place_error'], 1e3, '.1f', ' mm')} from its place, "
            f"{'upright' if s['upright'] else 'toppled'}, "
            f"{'released' if s['released'] else 'still touched'}; "
            f"{'grasped' if s['grasped'] else 'not grasped'}, approach disturbed it by "
            f"{_shown(s['approach_disturbance'], 1e3, '.2f', ' mm')}, done at "
            f"{_shown(s['time_to_place'], 1, '.1f', ' s')}"
        )
    if "penetration_max" in s:
        return (
            f"goal {'reached' if s['goal_reached'] else 'not reached'} (time to goal "
            f"{_shown(s['time_to_goal'], 1, '.2f', ' s')}, final error "
            f"{_shown(s['goal_error'], 1e3, '.2f', ' mm')}); penetration max "
            f"{_shown(s['penetration_max'], 1e3, '.2f', ' mm')}, contact impulse "
            f"{_shown(s['contact_impulse'], 1, '.3f', ' N s')}"
        )
    if "path_rms" in s:
        return (
            f"path error rms {_shown(s['path_rms'], 1e3, '.2f', ' mm')}, max "
            f"{_shown(s['path_max'], 1e3, '.2f', ' mm')}; {s['paths_tracked']} of {s['paths']} "
            "paths tracked"
        )
    if "rms_tracking_error" in s:
        return (
            f"rms tracking error {_shown(s['rms_tracking_error'], 1, '.3f', ' 1/m')}, max "
            f"overshoot {_shown(s['max_overshoot'], 100, '.1f', ' %')}, settling "
            f"{_shown(s['settling_time'], 1, '.2f', ' s')}, steady-state error "
            f"{_shown(s['steady_state_error'], 1, '.4f', ' 1/m')}"
        )
    if "heading_change" in s:  # the soft fish
        return (
            f"heading change {_shown(s['heading_change'], 1, '.1f', ' deg')} in "
            f"{_shown(s['turn_time'], 1e3, '.0f', ' ms')}, peak yaw rate "
            f"{_shown(s['peak_yaw_rate'], 1, '.0f', ' deg/s')}, peak acceleration "
            f"{_shown(s['peak_acceleration'], 1, '.1f', ' m/s^2')}, forward speed "
            f"{_shown(s['forward_speed'], 1, '.3f', ' m/s')}, gas used "
            f"{_shown(s['gas_used'], 1e6, '.0f', ' mg')}, {s['manoeuvres_left']} manoeuvres left; "
            f"{s['end_reason']}"
        )
    return "no task metrics"
