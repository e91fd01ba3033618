"""Benchmark: the cost of stepping the plant's FMUs, layer by layer, against the pure-C loop.

Every figure is a ratio against a baseline measured in the same process and run: the pure-C loop
(bench/pure_loop.c: the same FMU instances stepped with their coupling in one C call, no Python at
all: the physical limit). For 1, 2, 4 and 6 planar-arm segments (DriveCylinder + FeaSegment each,
coupled as in robots.planar_arm.plant.rig: cylinder.x -> segment.x_piston, segment.p_a/p_b ->
cylinder.p_a/p_b, a constant x_ref input), the same simulated time is stepped by
  pure C        one call of the C loop over every tick
  kernel        hil.cosim.Algorithm with the C kernel, advanced SYNC by SYNC (10 macro steps)
  python        hil.cosim.Algorithm(kernel=False), advanced SYNC by SYNC: the reference
  fmpy          fmpy alone: the same FMI calls from a Python loop, no master
reported as microseconds per FMU macro step, the ratio to the pure-C loop, and per layer the
fitted cost slope in microseconds per segment per SYNC. The issue 8 target: the kernel within 1.5x
of the pure-C loop. Then the closed loop on the default task for 1, 2, 4 and 6 segments:
  hil run --inprocess             plant and controller in one thread, direct bus
  hil run (separate process)      controller as a separate process over the loopback hub
with the kernel (and, for 1 segment, with SOFTHIL_KERNEL=0), as real-time factors and ratios
to the pure-C loop of the same segments. In-process the FMUs step to the next SYNC on the
kernel's worker thread while the controller computes; row "FMUs in turn" runs them one after the
other (SOFTHIL_KERNEL_THREAD=0). The separate process speaks softhil's binary records
to the hub the plant hosts in its own thread (the default); rows "hub process" and "hub thread"
run the hub as a child process (SOFTHIL_HUB=process) or a thread of the plant
(SOFTHIL_HUB=thread) instead, the alternatives it was chosen over; row "no busy poll" runs the
default with SOFTHIL_BUSY_POLL=0 (both processes sleep in select at once when they wait).
Before all that, the transport alone: the round trip of one frame from this process through the
hub (a child process) to an echoing peer process and back, for socketcand's ASCII and for the
binary records, in microseconds (median of --repeat batches). For 6 segments in-process the
closed loop also runs with `[controller] estimator` = raw and kf besides the default ukf, so the
estimator's share of the loop shows; and row "hil run --controller examples/piston_sine.py"
runs, across processes, a controller that only sends SYNC and commands a sine (no estimator, no
control law; python-can's socketcand client), so the plant's own side shows: the ceiling the
separate-process target meets with a controller that costs nothing.

Last, the per-SYNC budget by layer: the 6-segment closed loop in-process, once plain and once
instrumented, its wall time per SYNC split into layers (`BUDGET_LAYERS`): the FMUs in C (the
kernel: with its worker thread, what the loop waits for it, not what it computes), the
master's bookkeeping, the camera model, the DBC codec (both sides), the direct bus, the
recording, the controller's estimator and control law, the plant's and the controller's node
logic (dispatch, device firmware, frame collection), and the rest of the loop (other).
Instrumentation: perf_counter accumulators with exclusive attribution (`LayerBudget`): the bench
wraps the methods that enter a layer (`budget_wrappers`) for the instrumented run only and
restores them after, so the code under test holds no timing hooks and costs nothing when not
measured. A stack of open layers charges every interval between two clock reads to the layer
on top, so the layers add up to the loop's total exactly. Chosen over cProfile, whose per-call
overhead (about 60 % of this loop) falls on every Python call, so on the layers made of many
small calls far more than on the C calls (the FMUs, numpy), which distorts the shares; the
wrappers time only ~190 calls per SYNC (6 segments), a few microseconds each, charged to the
layers around them: the report gives the instrumented loop's time beside the plain one's.

Run from the checkout: PYTHONPATH=. python bench/bench_run.py [--repeat 3] [--seconds 2]
[--no-closed-loop] [--no-transport] [--no-budget] [--budget-only] [--json out.json]
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import functools
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np

from hil.bus.loopback import HubProcess
from hil.cosim import Algorithm, Connection, FmuParticipant
from hil.fmu.build import CFLAGS, compile_library
from hil.fmu.slave import FmuSlave
from hil.run import RunOptions, run_scenario
from hil.scenario import Scenario, load_scenario
from rigbus.canbus import BusSpec, open_bus

PURE_LOOP = Path(__file__).with_name("pure_loop.c")
ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_CONTROLLER = (
    f"{shlex.quote(sys.executable)} {shlex.quote(str(ROOT / 'examples' / 'piston_sine.py'))} "
    "--config {config} --interface {interface} --channel {channel} --host {host} --port {port}"
)
TRANSPORTS = {"socketcand": "loopback", "binary": "softhil"}  # name: bus spec kind
ECHO = """
import sys
from rigbus.canbus import BusSpec, open_bus
bus = open_bus(BusSpec(sys.argv[1], "softhil", "127.0.0.1", int(sys.argv[2])))
print("ready", flush=True)
while True:
    message = bus.recv(10.0)
    if message is None or message.arbitration_id == 0x7FF:
        break
    bus.send(message)
bus.shutdown()
"""
SEGMENTS = (1, 2, 4, 6)
X_REF = 0.03  # [m] constant setpoint: the pistons move, the pressures build
LAYERS = ("pure C", "kernel", "python", "fmpy")


class _Segment(ctypes.Structure):
    _fields_ = [
        *((name, ctypes.c_void_p) for name in ("cylinder", "segment")),
        *(
            (name, ctypes.c_void_p)
            for name in ("cyl_set", "cyl_get", "cyl_step", "seg_set", "seg_get", "seg_step")
        ),
        ("cyl_p", ctypes.c_uint * 2),
        ("cyl_x", ctypes.c_uint),
        ("seg_x", ctypes.c_uint),
        ("seg_p", ctypes.c_uint * 2),
    ]


def shared_library(stem: str, source: str, flags: Sequence[str]) -> ctypes.CDLL:
    """The C `source` built into a shared library with the package's compiler and `flags`, once
    per compiler, flags and source (cached as `bench/<stem>-<digest>.so` in the cache)."""
    return ctypes.CDLL(str(compile_library("bench", stem, source, flags)))


def pure_loop_library() -> ctypes.CDLL:
    library = shared_library("pure_loop", PURE_LOOP.read_text(), (*CFLAGS, "-ffp-contract=off"))
    library.pure_loop.restype = ctypes.c_int
    library.pure_loop.argtypes = [
        ctypes.POINTER(_Segment),
        ctypes.c_int,
        ctypes.c_longlong,
        ctypes.c_double,
    ]
    return library


@contextlib.contextmanager
def arm(segments: int) -> Iterator[list[tuple[FmuSlave, FmuSlave]]]:
    pairs = []
    try:
        for n in range(1, segments + 1):
            cylinder = FmuSlave("DriveCylinder", f"cylinder{n}", {"x_ref": X_REF})
            pairs.append((cylinder, FmuSlave("FeaSegment", f"segment{n}")))
        yield pairs
    finally:
        for cylinder, segment in pairs:
            cylinder.close()
            segment.close()


def pure_c(library: ctypes.CDLL, segments: int, ticks: int, h: float) -> float:
    with arm(segments) as pairs:
        table = (_Segment * segments)()
        for row, (cylinder, segment) in zip(table, pairs, strict=True):
            c_dll, row.cylinder = cylinder.fmi_handles()
            s_dll, row.segment = segment.fmi_handles()
            for field, dll, call in (
                ("cyl_set", c_dll, "fmi2SetReal"),
                ("cyl_get", c_dll, "fmi2GetReal"),
                ("cyl_step", c_dll, "fmi2DoStep"),
                ("seg_set", s_dll, "fmi2SetReal"),
                ("seg_get", s_dll, "fmi2GetReal"),
                ("seg_step", s_dll, "fmi2DoStep"),
            ):
                setattr(row, field, ctypes.cast(getattr(dll, call), ctypes.c_void_p).value)
            row.cyl_p[:] = [cylinder.value_reference("p_a"), cylinder.value_reference("p_b")]
            row.cyl_x = cylinder.value_reference("x")
            row.seg_x = segment.value_reference("x_piston")
            row.seg_p[:] = [segment.value_reference("p_a"), segment.value_reference("p_b")]
        start = time.perf_counter()
        status = library.pure_loop(table, segments, ticks, h)
        elapsed = time.perf_counter() - start
    if status != 0:
        raise RuntimeError(f"pure C loop failed with FMI status {status}")
    return elapsed


def master_layer(segments: int, ticks: int, h: float, kernel: bool, sync_ticks: int) -> float:
    with arm(segments) as pairs:
        participants: list[FmuParticipant] = []
        connections = []
        for n, (cylinder, segment) in enumerate(pairs, start=1):
            participants += [FmuParticipant(cylinder), FmuParticipant(segment)]
            connections += [
                Connection(f"cylinder{n}.x", f"segment{n}.x_piston"),
                Connection(f"segment{n}.p_a", f"cylinder{n}.p_a"),
                Connection(f"segment{n}.p_b", f"cylinder{n}.p_b"),
            ]
        master = Algorithm(participants, connections, h, kernel=kernel)
        assert master.uses_kernel == kernel
        for n in range(1, segments + 1):
            master.set_input(f"cylinder{n}", "x_ref", X_REF)
        start = time.perf_counter()
        for sync_tick in range(sync_ticks, ticks + 1, sync_ticks):
            master.advance_to(sync_tick)
        return time.perf_counter() - start


def fmpy_alone(segments: int, ticks: int, h: float) -> float:
    with arm(segments) as pairs:
        refs = []
        for cylinder, segment in pairs:
            cv = [cylinder.value_reference(name) for name in ("x", "p_a", "p_b")]
            sv = [segment.value_reference(name) for name in ("x_piston", "p_a", "p_b")]
            refs.append((cylinder, segment, cv, sv))
        state = [(cyl.get_reals(cv[:1])[0], seg.get_reals(sv[1:])) for cyl, seg, cv, sv in refs]
        start = time.perf_counter()
        for k in range(ticks):
            for (cylinder, segment, cv, sv), (x, p) in zip(refs, state, strict=True):
                cylinder.set_reals(cv[1:], p)
                segment.set_reals(sv[:1], [x])
                cylinder.do_step(k * h, h)
                segment.do_step(k * h, h)
            state = [(cyl.get_reals(cv[:1])[0], seg.get_reals(sv[1:])) for cyl, seg, cv, sv in refs]
        return time.perf_counter() - start


def full_run(
    scenario: Scenario,
    inprocess: bool,
    kernel: bool,
    hub: str = "plant",
    busy_poll: str | None = None,
    controller: str = "softhil",
    kernel_thread: str | None = None,
) -> float:
    settings = {"SOFTHIL_KERNEL": "1" if kernel else "0", "SOFTHIL_HUB": hub}
    if busy_poll is not None:
        settings["SOFTHIL_BUSY_POLL"] = busy_poll
    if kernel_thread is not None:
        settings["SOFTHIL_KERNEL_THREAD"] = kernel_thread
    # the environment as it was afterwards, a user's own settings included
    with mock.patch.dict(os.environ, settings), tempfile.TemporaryDirectory() as out:
        result = run_scenario(
            scenario,
            RunOptions(out=Path(out), inprocess=inprocess, progress=False, controller=controller),
        )
        return float(result.summary["wall_time"])


def round_trip(kind: str, frames: int, repeat: int) -> float:
    """Median over ``repeat`` batches of the round trip of one 8-byte frame [us]: this process
    -> hub (a child process) -> an echoing peer process -> hub -> this process."""
    import can

    hub = HubProcess()
    path = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    env = {**os.environ, "PYTHONPATH": path}
    peer = subprocess.Popen(
        [sys.executable, "-c", ECHO, kind, str(hub.port)],
        stdout=subprocess.PIPE,
        env=env,
        text=True,
    )
    bus = None
    try:
        assert peer.stdout is not None and peer.stdout.readline().strip() == "ready"
        bus = open_bus(BusSpec(kind, "softhil", "127.0.0.1", hub.port))
        message = can.Message(arbitration_id=0x181, is_extended_id=False, data=bytes(8))
        for _ in range(50):  # the socketcand client's handshake grace holds the first frames
            bus.send(message)
            if bus.recv(0.2) is not None:
                break
        while bus.recv(0.05) is not None:
            pass
        batches = []
        for _ in range(repeat):
            start = time.perf_counter()
            for _ in range(frames):
                bus.send(message)
                if bus.recv(5.0) is None:
                    raise RuntimeError(f"{kind}: the echo did not come back")
            batches.append((time.perf_counter() - start) / frames * 1e6)
        bus.send(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b""))
        return statistics.median(batches)
    finally:
        if bus is not None:
            bus.shutdown()
        peer.wait(timeout=10)
        hub.stop()


# ---------------------------------------------------------------------------- per-SYNC budget

BUDGET_LAYERS = (
    "FMUs (kernel)",
    "master",
    "camera",
    "codec",
    "bus",
    "recording",
    "estimator",
    "control law",
    "plant node",
    "controller node",
    "other",
)


class LayerBudget:
    """Exclusive wall time per layer [s], from perf_counter accumulators.

    `wrap(owner, name, layer)` replaces the callable attribute `name` of `owner` (a class or an
    instance) by one that opens `layer` for the duration of the call; `restore` puts every
    original back. Between `start` and `stop`, each interval between two clock reads is charged
    to the innermost open layer ("other" when none is), so `seconds` adds up to `total`.

    A wrapper costs time of its own: `inner` [s] per call inside its layer (from its first clock
    read to its last) and `outer` [s] per call in the layer that called it. `corrected` takes
    both out of the layers they were charged to (`nested` counts the wrapped calls each layer
    made); `calibrate` measures them on a wrapped no-op.

    Parameters
    ----------
    clock
        Monotonic clock [s]; injectable so that the attribution can be checked exactly.
    """

    def __init__(self, clock: Callable[[], float] = time.perf_counter) -> None:
        self.clock = clock
        self.seconds = dict.fromkeys(BUDGET_LAYERS, 0.0)  # of the last start..stop
        self.calls = dict.fromkeys(BUDGET_LAYERS, 0)
        self.nested = dict.fromkeys(BUDGET_LAYERS, 0)  # wrapped calls made from each layer
        self.total = 0.0
        # the accumulators run whenever a wrapped method runs (before the loop too: building
        # the master publishes); `start` zeroes them in place, `stop` copies them out
        self._seconds = dict(self.seconds)
        self._calls = dict(self.calls)
        self._nested = dict(self.nested)
        self._stack = ["other"]
        self._mark = [0.0]  # the last clock read, in a list the wrappers update in place
        self._started = 0.0
        self._patches: list[tuple[object, str, object]] = []

    def start(self) -> None:
        for layer in BUDGET_LAYERS:
            self._seconds[layer], self._calls[layer], self._nested[layer] = 0.0, 0, 0
        self._started = self._mark[0] = self.clock()

    def stop(self) -> None:
        now = self.clock()
        self._seconds[self._stack[-1]] += now - self._mark[0]
        self._mark[0] = now
        self.seconds, self.calls = dict(self._seconds), dict(self._calls)
        self.nested = dict(self._nested)
        self.total = now - self._started

    def corrected(self, inner: float, outer: float) -> dict[str, float]:
        """`seconds` less the wrappers' own time [s]: `inner` per call of the layer, `outer` per
        wrapped call it made (floored at 0)."""
        return {
            layer: max(0.0, seconds - self.calls[layer] * inner - self.nested[layer] * outer)
            for layer, seconds in self.seconds.items()
        }

    @staticmethod
    def calibrate(calls: int = 20000) -> tuple[float, float]:
        """(inner, outer) [s per call]: a wrapped no-op called `calls` times; outer is what the
        calling loop spent beyond the same loop over the bare no-op."""

        class Probe:
            def noop(self) -> None:
                pass

        probe = Probe()
        bare = probe.noop
        start = time.perf_counter()
        for _ in range(calls):
            bare()
        loop = time.perf_counter() - start
        budget = LayerBudget()
        budget.wrap(Probe, "noop", "codec")
        wrapped = probe.noop
        budget.start()
        for _ in range(calls):
            wrapped()
        budget.stop()
        budget.restore()
        inner = budget.seconds["codec"] / calls
        return inner, max(0.0, budget.seconds["other"] - loop) / calls

    def wrap(self, owner: object, name: str, layer: str) -> None:
        if layer not in self.seconds:
            raise ValueError(f"{layer!r} is not a budget layer ({', '.join(BUDGET_LAYERS)})")
        # on a class the plain function (the wrapper binds as a method), on an instance the
        # bound method
        original = getattr(owner, name)
        clock, seconds, calls, nested, stack, mark = (
            self.clock,
            self._seconds,
            self._calls,
            self._nested,
            self._stack,
            self._mark,
        )

        def timed(*args: object, **kwargs: object) -> object:
            # inlined, not method calls: the wrapper's own cost is what distorts the budget
            now = clock()
            seconds[stack[-1]] += now - mark[0]
            nested[stack[-1]] += 1
            stack.append(layer)
            calls[layer] += 1
            mark[0] = now
            try:
                return original(*args, **kwargs)
            finally:
                now = clock()
                seconds[stack.pop()] += now - mark[0]
                mark[0] = now

        self.patch(owner, name, timed)

    def patch(self, owner: object, name: str, value: object) -> None:
        """Set `owner.name` to `value` until `restore`."""
        self._patches.append((owner, name, vars(owner).get(name, _INHERITED)))
        setattr(owner, name, value)

    def restore(self) -> None:
        for owner, name, original in reversed(self._patches):
            if original is _INHERITED:
                delattr(owner, name)
            else:
                setattr(owner, name, original)
        self._patches.clear()


_INHERITED = object()  # an attribute the owner did not hold itself: restored by deleting


def budget_wrappers(budget: LayerBudget) -> None:
    """Wrap the entries of every layer of an in-process run, on the classes (before the run
    builds its objects); the controller's estimator and control law per instance, when the
    plant's driven run starts (`Plant.run_driven`'s driver is the controller node's `run`),
    which also brackets the budget's total."""
    from controllers.node import ControllerNode
    from hil.bus.direct import DirectBus
    from hil.cosim.kernel import Kernel
    from hil.devices import CameraNode
    from hil.plant import Plant
    from hil.recording import CanLogger, SignalRecorder
    from rigbus.protocol import Protocol

    for owner, names, layer in (
        (Kernel, ("advance", "start", "finish"), "FMUs (kernel)"),
        (FmuParticipant, ("step", "set_inputs", "get_outputs"), "FMUs (kernel)"),
        (Algorithm, ("advance_to", "publish", "inputs_of"), "master"),
        (CameraNode, ("step", "act"), "camera"),
        (Protocol, ("encode", "decode"), "codec"),
        (DirectBus, ("send", "recv"), "bus"),
        (CanLogger, ("log", "log_all", "flush"), "recording"),
        (SignalRecorder, ("begin_row", "set_cells", "end_row"), "recording"),
        (Plant, ("handle",), "plant node"),
        (ControllerNode, ("_collect", "_send", "_flush"), "controller node"),
    ):
        for name in names:
            budget.wrap(owner, name, layer)
    run_driven = Plant.run_driven

    def bracketed(plant: Plant, driver: Callable[[], object], *args: Any) -> Any:
        node = getattr(driver, "__self__", None)
        if isinstance(node, ControllerNode):
            budget.wrap(node.estimator, "update", "estimator")
            budget.wrap(node.controller, "compute", "control law")
        budget.start()
        try:
            return run_driven(plant, driver, *args)
        finally:
            budget.stop()

    budget.patch(Plant, "run_driven", bracketed)


def budget_scenario(scenario: Scenario, seconds: float, segments: int = 6) -> Scenario:
    """The default task on `segments` segments for `seconds` of simulated time (whole control
    periods), its sine moved past the end: the closed loop's benchmark scenario."""
    period = scenario.timing.control_period
    duration = round(seconds / period) * period
    robot = replace(scenario.robot, segments=segments)
    task = replace(scenario.task, sine=replace(scenario.task.sine, start=duration))
    return replace(scenario, robot=robot, duration=duration, task=task)


def sync_budget(scenario: Scenario) -> dict[str, Any]:
    """The scenario's closed loop in-process, plain and instrumented: per layer the exclusive
    wall time per SYNC [us] with the wrappers' own time taken out (`LayerBudget.corrected`),
    its share of the corrected total, its entries per SYNC and its time as measured; both
    loops' totals [us per SYNC]. A first plain run warms up (FMU loading, first calls)."""
    walls = []
    for _ in range(2):
        with tempfile.TemporaryDirectory() as out:
            options = RunOptions(out=Path(out), inprocess=True, progress=False)
            walls.append(float(run_scenario(scenario, options).summary["wall_time"]))
    budget = LayerBudget()
    budget_wrappers(budget)
    try:
        with tempfile.TemporaryDirectory() as out:
            options = RunOptions(out=Path(out), inprocess=True, progress=False)
            timed = run_scenario(scenario, options).summary
    finally:
        budget.restore()
    inner, outer = LayerBudget.calibrate()
    corrected = budget.corrected(inner, outer)
    total = sum(corrected.values())
    syncs = scenario.cycles + 1
    return {
        "segments": scenario.robot.segments,
        "syncs": syncs,
        "plain_us_per_sync": walls[-1] / syncs * 1e6,
        "instrumented_us_per_sync": float(timed["wall_time"]) / syncs * 1e6,
        "wrapper_us_per_call": {"inner": inner * 1e6, "outer": outer * 1e6},
        "measured_us_per_sync": budget.total / syncs * 1e6,
        "total_us_per_sync": total / syncs * 1e6,
        "layers": {
            layer: {
                "us_per_sync": seconds / syncs * 1e6,
                "share": seconds / total,
                "calls_per_sync": budget.calls[layer] / syncs,
                "measured_us_per_sync": budget.seconds[layer] / syncs * 1e6,
            }
            for layer, seconds in corrected.items()
        },
    }


def print_budget(report: Mapping[str, Any]) -> None:
    print(
        f"per-SYNC budget, {report['segments']} segments in-process, {report['syncs']} SYNCs: "
        f"plain {report['plain_us_per_sync']:.0f} us/SYNC, instrumented "
        f"{report['instrumented_us_per_sync']:.0f} us/SYNC; the wrappers' own time taken out "
        f"({report['wrapper_us_per_call']['inner']:.2f} us in the layer, "
        f"{report['wrapper_us_per_call']['outer']:.2f} us in its caller, per call)"
    )
    print(f"{'layer':>16s} {'us/SYNC':>9s} {'share':>7s} {'calls/SYNC':>11s} {'measured':>9s}")
    for layer, row in report["layers"].items():
        print(
            f"{layer:>16s} {row['us_per_sync']:9.1f} {row['share'] * 100:6.1f}% "
            f"{row['calls_per_sync']:11.1f} {row['measured_us_per_sync']:9.1f}"
        )
    print(
        f"{'total':>16s} {report['total_us_per_sync']:9.1f} {100.0:6.1f}% {'':11s} "
        f"{report['measured_us_per_sync']:9.1f}"
    )


def median(repeat: int, f: Callable[[], float]) -> float:
    return statistics.median(f() for _ in range(repeat))


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeat", type=int, default=3, help="runs per layer (median taken)")
    parser.add_argument("--seconds", type=float, default=2.0, help="simulated time per run [s]")
    parser.add_argument("--no-closed-loop", action="store_true", help="skip the hil run rows")
    parser.add_argument(
        "--no-transport", action="store_true", help="skip the transport round-trip rows"
    )
    parser.add_argument("--no-budget", action="store_true", help="skip the per-SYNC budget")
    parser.add_argument(
        "--budget-only", action="store_true", help="only the per-SYNC budget (6 segments)"
    )
    parser.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = parser.parse_args()
    scenario = load_scenario()
    scenario = replace(scenario, bus=replace(scenario.bus, kind="loopback", port=0))
    if args.budget_only:
        budget = sync_budget(budget_scenario(scenario, args.seconds))
        print_budget(budget)
        if args.json:
            args.json.write_text(json.dumps({"budget": budget}, indent=2) + "\n")
        return 0
    h = scenario.timing.step
    sync_ticks = scenario.control_ticks
    ticks = round(args.seconds / h) // sync_ticks * sync_ticks
    syncs = ticks // sync_ticks
    transport: dict[str, float] = {}
    if not args.no_transport:
        print("transport: round trip of one frame through the hub process to a peer process [us]")
        for name, kind in TRANSPORTS.items():
            transport[name] = round_trip(kind, 500, max(args.repeat, 3))
            print(f"{name:>12s} {transport[name]:9.1f} us")
        ratio = transport["socketcand"] / transport["binary"]
        print(f"{'':>12s} binary is {ratio:.2f}x faster")
    library = pure_loop_library()
    fmpy_alone(1, 10, h)  # warm up: build/load the FMUs once
    layers: dict[str, Callable[[int], float]] = {
        "pure C": lambda n: pure_c(library, n, ticks, h),
        "kernel": lambda n: master_layer(n, ticks, h, True, sync_ticks),
        "python": lambda n: master_layer(n, ticks, h, False, sync_ticks),
        "fmpy": lambda n: fmpy_alone(n, ticks, h),
    }
    print(
        f"{args.seconds:g} s simulated ({ticks} macro steps of {h * 1e3:g} ms, {syncs} SYNCs), "
        f"median of {args.repeat}; us per FMU macro step (x pure C)"
    )
    print(f"{'segments':>8s} " + " ".join(f"{name:>18s}" for name in LAYERS))
    rows: dict[str, dict[str, dict[str, float]]] = {}
    for n in SEGMENTS:
        walls = {name: median(args.repeat, lambda f=f, n=n: f(n)) for name, f in layers.items()}
        base = walls["pure C"]
        fmu_steps = ticks * 2 * n
        rows[str(n)] = {
            name: {
                "wall_time": wall,
                "us_per_fmu_step": wall / fmu_steps * 1e6,
                "ratio_to_pure_c": wall / base,
            }
            for name, wall in walls.items()
        }
        cells = [f"{wall / fmu_steps * 1e6:9.2f} ({wall / base:5.2f}x)" for wall in walls.values()]
        print(f"{n:8d} " + " ".join(f"{cell:>18s}" for cell in cells))
    slopes = {}
    for name in LAYERS:
        per_sync = [rows[str(n)][name]["wall_time"] / syncs * 1e6 for n in SEGMENTS]
        slope, intercept = np.polyfit(SEGMENTS, per_sync, 1)
        slopes[name] = {"us_per_segment_per_sync": slope, "us_per_sync_intercept": intercept}
    print("fitted cost per SYNC [us] = slope * segments + intercept")
    for name, fit in slopes.items():
        print(
            f"{name:>8s}: {fit['us_per_segment_per_sync']:9.1f} us/segment/SYNC "
            f"({fit['us_per_segment_per_sync'] / slopes['pure C']['us_per_segment_per_sync']:.2f}"
            f"x pure C), intercept {fit['us_per_sync_intercept']:7.1f} us"
        )
    closed: dict[str, dict[str, float]] = {}
    if not args.no_closed_loop:
        duration = round(args.seconds / scenario.timing.control_period) * (
            scenario.timing.control_period
        )
        print(f"closed loop, default task: {duration:g} s simulated; real-time factor (RTF)")
        print(f"{'layer':44s} {'segments':>8s} {'wall [s]':>9s} {'RTF':>7s} {'x pure C':>9s}")
        for n in SEGMENTS:
            arm = budget_scenario(scenario, args.seconds, n)
            base = rows[str(n)]["pure C"]["wall_time"] / ticks  # per macro step, n segments
            # (in-process, hub, kernel, estimator, SOFTHIL_BUSY_POLL or, in-process,
            # SOFTHIL_KERNEL_THREAD)
            variants: list[tuple[bool, str, bool, str | None, str | None]]
            variants = [(True, "plant", True, None, None), (True, "plant", True, None, "0")]
            variants += [(False, "plant", True, None, None)]
            variants += [(False, "plant", False, None, None)] if n == 1 else []
            variants += [(False, "plant", True, None, "0")]
            variants += [(False, "process", True, None, None), (False, "thread", True, None, None)]
            # the estimator's share: the same loop with the cheaper estimators
            variants += [(True, "plant", True, e, None) for e in ("raw", "kf")] if n == 6 else []
            # the plant's side alone across processes: a controller that only commands a sine
            # (examples/piston_sine.py: no estimator, python-can's socketcand client)
            variants += [(False, "plant", True, "piston_sine", None)]
            for inprocess, hub, kernel, estimator, switch in variants:
                name = "hil run --inprocess" if inprocess else "hil run (separate process)"
                name += "" if kernel else " SOFTHIL_KERNEL=0"
                name += "" if hub == "plant" or inprocess else f", hub {hub}"
                name += f", estimator {estimator}" if estimator else ""
                if inprocess:
                    busy_poll, kernel_thread = None, switch
                    name += ", FMUs in turn" if switch == "0" else ""
                else:
                    busy_poll, kernel_thread = switch, None
                    name += ", no busy poll" if switch == "0" else ""
                run, program = arm, "softhil"
                if estimator == "piston_sine":
                    name = "hil run --controller examples/piston_sine.py"
                    program = EXAMPLE_CONTROLLER
                elif estimator:
                    run = replace(arm, controller=replace(arm.controller, estimator=estimator))
                case = functools.partial(
                    full_run, run, inprocess, kernel, hub, busy_poll, program, kernel_thread
                )
                wall = median(args.repeat, case)
                ratio = wall / (base * round(duration / h))
                closed[f"{name} / {n}"] = {
                    "segments": n,
                    "wall_time": wall,
                    "real_time_factor": duration / wall,
                    "ratio_to_pure_c": ratio,
                }
                print(f"{name:44s} {n:8d} {wall:9.3f} {duration / wall:7.1f} {ratio:9.2f}")
    budget: dict[str, Any] = {}
    if not args.no_budget:
        budget = sync_budget(budget_scenario(scenario, args.seconds))
        print_budget(budget)
    if args.json:
        report = {
            "machine": {"cpus": os.cpu_count(), "load_average": os.getloadavg()},
            "transport_round_trip_us": transport,
            "ticks": ticks,
            "segments": rows,
            "slopes": slopes,
            "closed_loop": closed,
            "budget": budget,
        }
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
