"""The soft fish (README, "The soft fish"; issue 13) as a robot kind: a GasSource FMU (the CO2
canister and its regulator), two FishValve FMUs (one per tail channel) and a FishBody FMU (head
free in the plane, tapered three-piece tail), a valve driver per valve and the canister's monitor
on the bus, and the overhead camera seeing the nose, the head-tail joint and the tail tip.

`[robot]` keys: `base` (start x [m], y [m], yaw [rad]); per-FMU parameter tables `source`,
`valve` (both valves; `[robot.valve.1]`/`[robot.valve.2]` override one, as the arm's per-actuator
tables) and `body`. The task: `[task] kind` = "escape" | "swim" | "heading", with the fish's own
task keys in `[robot]` (`start`, `side`, `turn_angle` [deg], `frequency`, `duty`, `heading`
[deg]) so that `[task]` stays the arm's. The escape's valve-open time is `[robot.valve]
open_time` [s] (so `hil sweep fish-escape --set valve.open_time=...` sweeps it): it goes to the
controller, never to the FMUs; 0 or absent takes it from the calibration for `turn_angle`.

Invariant: gas moves only through the valves' nozzles and vents, whose flows FishBody integrates
with the channels' gas (the valves publish their effective areas); the canister loses what the
body reports drawn, a step later (the three FMUs conserve its mass to rounding,
tests/test_fish_fmus.py); metrics are computed from the true signals, never from what the
controller estimated.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from hil.cosim import Connection, FmuParticipant, Participant
from hil.devices import HEARTBEAT_PERIOD, CameraNode
from hil.rig import PlotSpec, Rig, SignalSpec, fmu_ref, scenario_camera
from hil.schema import Dbc, Key, Needs, OneOf, Range, Ref, Rule, Table, positive, setting
from hil.seam import camera_timing
from rigbus.protocol import Protocol
from robots.fish.controller import CALIBRATION, TASKS, FishConfig
from robots.fish.plant.devices import CanisterNode, ValveNode

if TYPE_CHECKING:
    from hil.scenario import Scenario

TABLES = {"source": "GasSource", "valve": "FishValve", "body": "FishBody"}
VALVES = 2
CONTROLLER_KEYS = ("open_time",)  # keys of [robot.valve] for the controller, not the FMU
CAMERA_MARKERS = (("nose_x", "nose_y"), ("x", "y"), ("tail_3_x", "tail_3_y"))
STAGE_ONE_ONSET = 0.01  # of the peak yaw rate: the head has started to turn


START_POSE = ("x_start", "y_start", "yaw_start")  # FishBody's, set from robot.base
START_WHY = "the start pose is robot.base"
TURN_MAX = math.degrees(CALIBRATION[-1][1])  # [deg] the calibration's largest turn
VALVE_TABLE = Table(
    "robot.valve",
    (
        Key(
            "open_time",
            float,
            0.0,
            "s",
            "escape: the valve's open time, for the controller (0: from turn_angle)",
            Range(0, Dbc("ValveCommand1", "open_time")),
        ),
    ),
    fmu="FishValve",
    doc="both valves' FishValve parameters; [robot.valve.1] and [robot.valve.2] one valve's",
)


@dataclass(frozen=True)
class FishSpec:
    """The `[robot]` section of the soft fish: its start pose, its FMUs' parameter tables and
    the keys of its tasks (escape, swim, heading: see robots/fish/plant/rig.py)."""

    kind: str = setting("fish", doc="the robot kind")
    base: tuple[float, float, float] = setting(
        (0.0, 0.0, 0.0), "m, m, rad", "the start: x, y, yaw (of the head-tail joint)"
    )
    source: dict[str, Any] = setting(factory=dict, doc="GasSource parameters ([robot.source])")
    valve: dict[str, Any] = setting(factory=dict, doc="FishValve parameters ([robot.valve])")
    body: dict[str, Any] = setting(factory=dict, doc="FishBody parameters ([robot.body])")
    start: float = setting(
        0.05, "s", "the first manoeuvre", Range(0, Ref("duration"), hi_open=True, why="the run")
    )
    side: int = setting(
        1,
        doc="escape: the valve that fires",
        choices={1: "channel a, turn left", 2: "channel b, turn right"},
    )
    turn_angle: float = setting(
        60.0,
        "deg",
        "escape: the kept heading change wanted (without robot.valve.open_time)",
        Range(0, TURN_MAX, lo_open=True, why="the calibration"),
    )
    # a stroke every half beat, opened and closed on the controller's clock: a shorter half beat
    # would fall behind a stroke per cycle and beat slower than asked
    frequency: float = setting(
        2.0,
        "Hz",
        "swim, heading: tail beats per second",
        Range(
            0,
            Ref("timing.control_period", 0.25, per=True),
            lo_open=True,
            why="a half beat of at least two control periods: 0.25 / timing.control_period",
        ),
    )
    duty: float = setting(
        0.1,
        "",
        "swim, heading: the share of each half beat a valve is open",
        Range(0, 1, lo_open=True),
    )
    heading: float = setting(60.0, "deg", "heading task: the commanded heading", Range(-180, 180))
    # the top of ValveStatus.p_channel, above the 400 kPa abs supply (a fault, not a working limit)
    max_channel_pressure: float = setting(
        300e3, "Pa", "the valve driver vents beyond it (gauge)", positive()
    )

    RULES: ClassVar[tuple[Rule, ...]] = (
        Needs("task.kind", OneOf(TASKS)),
        Needs("timing.step", Range(hi=1e-3), why="the fish's valves", unit="s"),
    )
    TABLES: ClassVar[tuple[Table, ...]] = (
        Table(
            "robot.source",
            (),
            fmu="GasSource",
            checked=False,
            doc="the canister's GasSource parameters",
        ),
        VALVE_TABLE,
        Table(
            "robot.body",
            (),
            fmu="FishBody",
            checked=False,
            doc="the body's FishBody parameters",
            refused=START_POSE,
            refused_why=START_WHY,
        ),
    )


SIGNALS: tuple[tuple[str, str, str, str], ...] = (
    ("x", "m", "head-tail joint x", "body.x"),
    ("y", "m", "head-tail joint y", "body.y"),
    ("yaw", "rad", "heading of the head (unwrapped)", "body.yaw"),
    ("yaw_rate", "rad/s", "yaw rate of the head", "body.yaw_rate"),
    ("surge", "m/s", "velocity of the joint along the heading", "body.surge"),
    ("a_head", "m/s^2", "acceleration of the head's centroid", "body.a_head"),
    ("nose_x", "m", "nose x", "body.nose_x"),
    ("nose_y", "m", "nose y", "body.nose_y"),
    *(
        (f"tail_{j}_{c}", "m", f"end of tail piece {j}, {c}", f"body.tail_{j}_{c}")
        for j in (1, 2, 3)
        for c in ("x", "y")
    ),
    *((f"theta_{j}", "rad", f"bend angle of tail piece {j}", f"body.theta_{j}") for j in (1, 2, 3)),
    ("p_a", "Pa", "gauge pressure of channel a (valve 1)", "body.p_a"),
    ("p_b", "Pa", "gauge pressure of channel b (valve 2)", "body.p_b"),
    ("opening_1", "", "valve 1 spool position (1 open to the supply)", "valve1.opening"),
    ("opening_2", "", "valve 2 spool position", "valve2.opening"),
    ("open_1", "", "valve 1 commanded open by its driver", "valve_driver1.open"),
    ("open_2", "", "valve 2 commanded open by its driver", "valve_driver2.open"),
    ("valve_state_1", "", "valve 1 state (ValveStatus)", "valve_driver1.state"),
    ("valve_state_2", "", "valve 2 state (ValveStatus)", "valve_driver2.state"),
    ("p_supply", "Pa", "regulated supply pressure (absolute)", "source.p_supply"),
    ("p_canister", "Pa", "canister pressure (absolute)", "source.p_canister"),
    ("m_canister", "kg", "gas in the canister", "source.m_canister"),
    ("empty", "", "1 once the canister cannot hold the set pressure", "source.empty"),
    ("m_vented", "kg", "gas vented to the water so far", "body.m_vented"),
    ("W_gas", "J", "work done by the gas on the tail so far", "body.W_gas"),
    ("E_elastic", "J", "elastic energy stored in the tail", "body.E_elastic"),
    ("E_kinetic", "J", "kinetic energy of fish and entrained water", "body.E_kinetic"),
    ("E_resistive", "J", "energy dissipated so far (drag, wake, damping)", "body.E_resistive"),
)
STATE_SIGNALS: tuple[tuple[str, str, str], ...] = (
    ("mode", "", "controller mode (FishState: idle, escape, swim, turn, hold, venting, no gas)"),
    ("manoeuvre", "", "manoeuvres commanded so far, as the controller reported it"),
    ("heading_ref", "rad", "commanded heading, as the controller reported it"),
    ("heading_est", "rad", "controller's heading estimate (wrapped), as it reported it"),
    ("manoeuvres_left", "", "manoeuvres the gas left allows, as the controller reported it"),
)


class Fish:
    name = "fish"
    spec_class = FishSpec
    estimation_report = False  # `hil estimate` scores the arm's curvature estimators

    # ------------------------------------------------------------------ parameters

    def given(self, scenario: Scenario, table: str, index: int = 1) -> dict[str, float]:
        """FMU parameters the scenario sets for `table` ("source", "valve" with the valve's
        index, "body"), without the controller's keys."""
        return {k: v for k, (v, _) in self._given(scenario, table, index).items()}

    def _given(self, scenario: Scenario, table: str, index: int) -> dict[str, tuple[float, str]]:
        from hil.scenario import fail
        from robots.planar_arm.plant.parameters import _number

        raw: dict[str, Any] = getattr(scenario.robot, table)
        out: dict[str, tuple[float, str]] = {}
        for name, value in raw.items():
            key = f"robot.{table}.{name}"
            if name in CONTROLLER_KEYS and table == "valve":
                continue
            if table == "valve" and name.isdigit():
                if int(name) not in range(1, VALVES + 1):
                    raise fail(scenario.source, key, f"no valve {name} (the fish has {VALVES})")
                if not isinstance(value, dict):
                    raise fail(scenario.source, key, "must be a table of parameters")
                continue
            out[name] = (_number(scenario.source, key, value), key)
        if table == "valve":
            per = raw.get(str(index), {})
            for name, value in per.items():
                sub = f"robot.valve.{index}.{name}"
                out[name] = (_number(scenario.source, sub, value), sub)
        return out

    def parameters(self, scenario: Scenario, table: str, index: int = 1) -> dict[str, float]:
        """Every parameter: what the scenario sets, else the FMU's default."""
        from hil.scenario import fmu_interface

        defaults = {
            name: port.start
            for name, port in fmu_interface(
                scenario.source, f"robot.{table}", TABLES[table]
            ).items()
            if port.causality == "parameter" and port.start is not None
        }
        return {**defaults, **self.given(scenario, table, index)}

    def open_time(self, scenario: Scenario) -> float:
        """`[robot.valve] open_time` [s], 0 where not given."""
        value = scenario.robot.valve.get("open_time", 0.0)
        return float(value)

    def camera_view(self, scenario: Scenario, protocol: Protocol | None = None) -> float:
        """Half the side of the square the camera sees [m]: the DBC's marker range less the
        camera's noise and outlier margin, so that what is seen stays within the range."""
        view = (protocol or Protocol()).signal_range("CameraMarker0", "x")[1]
        return (
            view
            - 5.0 * scenario.camera.noise
            - (scenario.camera.outlier_distance if scenario.camera.outlier_rate else 0.0)
        )

    def body_length(self, scenario: Scenario) -> float:
        body = self.parameters(scenario, "body")
        return float(body["L_head"] + body["L_1"] + body["L_2"] + body["L_3"])

    # ------------------------------------------------------------------ checks

    def check(self, scenario: Scenario) -> None:
        """The fish's checks that are code (its keys and rules are FishSpec's)."""
        from hil.scenario import check_parameter, fail, fmu_interface

        s, file, r = scenario, scenario.source, scenario.robot
        for table, model in TABLES.items():
            interface = fmu_interface(file, f"robot.{table}", model)
            for index in range(1, (VALVES if table == "valve" else 1) + 1):
                for name, (value, key) in self._given(s, table, index).items():
                    if name in START_POSE:
                        raise fail(file, key, START_WHY)
                    check_parameter(file, key, interface, name, value)
        stroke = r.duty * 0.5 / r.frequency  # a swim stroke's valve-open time [s]
        if s.task.kind in ("swim", "heading") and stroke < s.timing.step - 1e-12:
            # the valve driver opens for whole steps: a shorter stroke never opens it
            raise fail(
                file,
                "robot.duty",
                f"a stroke opens the valve for duty / (2 frequency) = {stroke * 1e3:.3g} ms, "
                f"less than one step of {s.timing.step * 1e3:g} ms, so no valve would open; "
                f"raise robot.duty (got {r.duty:g}) or lower robot.frequency "
                f"(got {r.frequency:g} Hz)",
            )
        if s.camera and s.camera.rate and len(CAMERA_MARKERS) > Protocol().count("CameraMarker"):
            raise fail(file, "camera", "more markers than the DBC's CameraMarker frames")

    def ports(self, scenario: Scenario) -> dict[str, tuple[set[str], set[str]]]:
        from hil.scenario import fmu_interface

        ports: dict[str, tuple[set[str], set[str]]] = {
            "camera": (set(), {f"{m}_{c}" for m in ("nose", "joint", "tip") for c in "xy"})
        }
        names = {"source": ["source"], "valve": ["valve1", "valve2"], "body": ["body"]}
        for table, model in TABLES.items():
            interface = fmu_interface(scenario.source, f"robot.{table}", model)
            for name in names[table]:
                ports[name] = (
                    {n for n, v in interface.items() if v.causality == "output"},
                    {n for n, v in interface.items() if v.causality == "input"},
                )
        for n in (1, 2):
            ports[f"valve_driver{n}"] = ({"open", "state"}, {"opening", "p_channel", "p_supply"})
        ports["canister"] = (set(), {"p_canister", "p_supply", "m_canister"})
        return ports

    def reach(self, scenario: Scenario) -> float:
        """Farthest a marker can be from the head-tail joint (the start point, `base`) [m]: the
        head or the tail, whichever is longer. (Swimming takes the fish further: a marker out of
        the camera's view is not seen, see `build`.)"""
        body = self.parameters(scenario, "body")
        return float(max(body["L_head"], body["L_1"] + body["L_2"] + body["L_3"]))

    # ------------------------------------------------------------------ the rig

    def build(self, scenario: Scenario) -> Rig:
        """GasSource -> two FishValves -> FishBody: the valves' nozzle and vent areas and the supply
        pressure and temperature into the body, the mass drawn back to the source
        (FishValve/model.c); the drivers set the valves' commands and read the channel and
        supply pressures; the canister monitor reads the source; the camera sees the nose, the
        joint and the tail tip (out of the camera's view: not seen)."""
        from hil.fmu.slave import FmuSlave

        r: FishSpec = scenario.robot
        protocol = Protocol()
        source_p = self.parameters(scenario, "source")
        body_given = {
            **self.given(scenario, "body"),
            "x_start": r.base[0],
            "y_start": r.base[1],
            "yaw_start": r.base[2],
        }
        drivers = [
            ValveNode(
                n,
                scenario.timing.step,
                source_p["p_set"],
                r.max_channel_pressure,
                protocol.signal_range("ValveStatus1", "p_channel"),
                heartbeat_node=n,
            )
            for n in (1, 2)
        ]
        canister = CanisterNode(
            {
                name: protocol.signal_range("CanisterStatus", name)
                for name in ("p_canister", "p_supply", "gas_left")
            }
        )
        seen = self.camera_view(scenario, protocol)

        def markers(values: Sequence[float]) -> np.ndarray:
            # a marker beyond the camera's field of view is not seen
            points = np.array(values, dtype=float).reshape(len(CAMERA_MARKERS), 2)
            points[np.abs(points).max(axis=1) > seen] = np.nan
            return points

        camera_inputs = [f"{m}_{c}" for m in ("nose", "joint", "tip") for c in "xy"]
        camera = CameraNode(
            camera_inputs,
            markers,
            scenario.latency_ticks,
            scenario_camera(scenario),
        )
        fmus: list[FmuParticipant] = []
        parameters: dict[str, Mapping[str, float]] = {}
        try:
            source = FmuSlave(
                fmu_ref(scenario.source, TABLES["source"]),
                "source",
                self.given(scenario, "source"),
                exit_initialization=False,  # until the master has set the connected inputs
            )
            fmus.append(FmuParticipant(source, 1))
            parameters["source"] = source_p
            for n in (1, 2):
                valve = FmuSlave(
                    fmu_ref(scenario.source, TABLES["valve"]),
                    f"valve{n}",
                    self.given(scenario, "valve", n),
                    exit_initialization=False,
                )
                fmus.append(FmuParticipant(valve, 1))
                parameters[f"valve{n}"] = self.parameters(scenario, "valve", n)
            body = FmuSlave(
                fmu_ref(scenario.source, TABLES["body"]),
                "body",
                body_given,
                exit_initialization=False,
            )
            fmus.append(FmuParticipant(body, 1))
            parameters["body"] = {**self.parameters(scenario, "body"), **body_given}
        except BaseException:
            for participant in fmus:
                participant.close()
            raise
        connections: dict[str, Connection] = {}
        links = [
            ("body.mdot_in_a", "source.mdot_a"),
            ("body.mdot_in_b", "source.mdot_b"),
            ("source.p_supply", "body.p_supply"),
            ("source.T_supply", "body.T_supply"),
            ("source.p_canister", "canister.p_canister"),
            ("source.p_supply", "canister.p_supply"),
            ("source.m_canister", "canister.m_canister"),
        ]
        for n, side in ((1, "a"), (2, "b")):
            links += [
                (f"valve{n}.CdA_in", f"body.CdA_in_{side}"),
                (f"valve{n}.CdA_vent", f"body.CdA_vent_{side}"),
                (f"valve_driver{n}.open", f"valve{n}.open"),
                (f"valve{n}.opening", f"valve_driver{n}.opening"),
                (f"body.p_{side}", f"valve_driver{n}.p_channel"),
                ("source.p_supply", f"valve_driver{n}.p_supply"),
            ]
        for marker, (cx, cy) in zip(("nose", "joint", "tip"), CAMERA_MARKERS, strict=True):
            links += [(f"body.{cx}", f"camera.{marker}_x"), (f"body.{cy}", f"camera.{marker}_y")]
        for source_name, target in links:
            connections[target] = Connection(source_name, target)
        for c in scenario.connections:
            connections[c.target] = Connection(c.source, c.target, c.gain, c.offset)
        participants: list[Participant] = [*fmus, *drivers, canister, camera]
        return Rig(
            participants,
            list(connections.values()),
            [*drivers, canister, camera],
            self.signals(scenario),
            self.plots(scenario),
            parameters,
            [("fish", lambda signals, path: draw_fish(self, scenario, signals, path))],
            animation=("fish", lambda signals, path, fmt: _animate(scenario, signals, path, fmt)),
        )

    def signals(self, scenario: Scenario) -> list[SignalSpec]:
        specs = [SignalSpec(c, u, d, source=s) for c, u, d, s in SIGNALS]
        specs += [SignalSpec(c, u, d, frame=("FishState", None, c)) for c, u, d in STATE_SIGNALS]
        return specs

    def plots(self, scenario: Scenario) -> list[PlotSpec]:
        lines: tuple[tuple[str, str, float, dict[str, str]], ...] = (
            ("yaw", "heading (true)", 180.0 / math.pi, {"color": "tab:blue"}),
            ("heading_est", "estimate (wrapped)", 180.0 / math.pi, {"color": "tab:orange"}),
        )
        if scenario.task.kind == "heading":  # the other tasks have no reference
            lines += (
                ("heading_ref", "reference", 180.0 / math.pi, {"color": "black", "ls": "--"}),
            )
        lines += (("yaw_rate", "yaw rate / 10", 18.0 / math.pi, {"color": "tab:green"}),)
        return [
            PlotSpec(
                "heading", "heading [deg], yaw rate [deg/s] / 10", ("heading and yaw rate",), lines
            ),
            PlotSpec(
                "pressures",
                "gauge pressure [kPa]",
                ("channels",),
                (
                    ("p_a", "channel a (valve 1)", 1e-3, {"color": "tab:red"}),
                    ("p_b", "channel b (valve 2)", 1e-3, {"color": "tab:green"}),
                ),
            ),
            PlotSpec(
                "valves",
                "valve state / spool",
                ("valve 1", "valve 2"),
                (
                    ("valve_state_{n}", "state (0 closed .. 3 venting)", 1.0, {"color": "black"}),
                    ("opening_{n}", "spool position", 1.0, {"color": "tab:purple"}),
                ),
            ),
        ]

    def frame_rates(self, scenario: Scenario, protocol: Protocol) -> dict[str, float]:
        per_period = 1.0 / scenario.timing.control_period
        rates: dict[str, float] = {
            "SYNC": per_period,
            "CanisterStatus": per_period,
            "FishState": per_period,
        }
        for n in (1, 2):
            rates[f"ValveStatus{n}"] = per_period
            rates[f"ValveCommand{n}"] = per_period
        for n in (1, 2, 3):
            rates[f"Heartbeat{n}"] = 1.0 / HEARTBEAT_PERIOD
        rates["CameraFrame"] = scenario.camera.rate
        for m in range(len(CAMERA_MARKERS)):
            rates[f"CameraMarker{m}"] = scenario.camera.rate
        return rates

    # ------------------------------------------------------------------ the controller side

    def controller_config(self, scenario: Scenario) -> FishConfig:
        r: FishSpec = scenario.robot
        source = self.parameters(scenario, "source")
        body = self.parameters(scenario, "body")
        rt = source["R_gas"] * source["T_canister"]
        # the mass at which the canister falls below the set pressure (GasSource/model.c)
        rho_v = source["rho_vapour"]
        b = (rho_v * rt / source["p_vapour"] - 1.0) / rho_v
        reserve = source["V_canister"] * source["p_set"] / (rt - b * source["p_set"])
        return FishConfig(
            robot=self.name,
            control_period=scenario.timing.control_period,
            cycles=scenario.cycles,
            camera_timing=camera_timing(scenario, len(CAMERA_MARKERS)),
            task=scenario.task.kind,
            start=r.start,
            side=r.side,
            turn_angle=math.radians(r.turn_angle),
            open_time=self.open_time(scenario),
            frequency=r.frequency,
            duty=r.duty,
            heading=math.radians(r.heading),
            p_set=source["p_set"],
            gas_reserve=reserve,
            camera_noise=max(scenario.camera.noise, 1e-5),
            head_length=body["L_head"],
            policy=scenario.controller.policy,
            timeout=scenario.controller.timeout,
        )

    # ------------------------------------------------------------------ scoring

    def task_metrics(self, scenario: Scenario, signals: Mapping[str, Any]) -> dict[str, Any]:
        from robots.fish.plant.metrics import fish_metrics

        return fish_metrics(self, scenario, signals)


def _animate(scenario: Scenario, signals: Mapping[str, Any], path: Path, fmt: str) -> None:
    from robots.fish.plant.animation import animate_fish

    animate_fish(scenario.name, signals, path, fmt)


def draw_fish(robot: Fish, scenario: Scenario, signals: Mapping[str, Any], path: Path) -> None:
    """The body's outline from above (nose, joint, tail pieces) at snapshots over the run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = signals["time"]
    fig, ax = plt.subplots(figsize=(7, 7))
    snapshots = np.unique(np.linspace(0, t.size - 1, 12).round().astype(int))
    colours = plt.cm.viridis(np.linspace(0, 1, snapshots.size))
    for k, colour in zip(snapshots, colours, strict=True):
        xs = [signals["nose_x"][k], signals["x"][k]] + [
            signals[f"tail_{j}_x"][k] for j in (1, 2, 3)
        ]
        ys = [signals["nose_y"][k], signals["y"][k]] + [
            signals[f"tail_{j}_y"][k] for j in (1, 2, 3)
        ]
        ax.plot(xs, ys, "-o", color=colour, ms=3, label=f"t = {t[k]:.2f} s")
        ax.plot(xs[0], ys[0], "^", color=colour, ms=7)
    ax.plot(signals["x"], signals["y"], ":", color="grey", lw=1, label="joint path")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{scenario.name}: the fish from above (triangle: nose)")
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


ROBOT = Fish()
