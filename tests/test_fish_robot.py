"""The soft fish as a robot kind, end to end (issue 13): the escape sweep through `hil sweep`
against the published and biological figures, the nozzle's effect, the work split, swimming,
the closed-loop heading with the realistic camera, a canister running down, determinism across
in-process and process mode; and the pieces: valve driver timing, the controller's dispatch,
the calibration, the scenario's one-line errors."""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from controllers.config import read_config
from hil.cli import main
from hil.devices import SyncContext
from hil.run import controller_config
from hil.scenario import ScenarioError, load_scenario, resolve_scenario
from rigbus.protocol import GenericFrame
from robots.fish.controller import CALIBRATION, FishConfig, open_time_for
from robots.fish.plant.devices import CLOSED, OPEN, OPENING, VENTING, ValveNode
from tests.helpers import run_summary as run
from tests.helpers import scenario_variant as scenario_file

OPEN_TIMES = (0.02, 0.04, 0.06, 0.08, 0.10, 0.12)


# ------------------------------------------------------------------ the escape sweep


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> list[dict]:
    out = tmp_path_factory.mktemp("fish") / "sweep"
    values = ",".join(f"{t:g}" for t in OPEN_TIMES)
    code = main(["sweep", "fish-escape", "--set", f"valve.open_time={values}", "--workers", "2",
                 "--out", str(out), "--no-progress"])  # fmt: skip
    assert code == 0
    trials = json.loads((out / "batch.json").read_text())["trials"]
    assert [t["overrides"]["robot.valve.open_time"] for t in trials] == list(OPEN_TIMES)
    summaries = []
    for t in trials:
        summary = json.loads((out / t["folder"] / "summary.json").read_text())
        signals = np.genfromtxt(out / t["folder"] / "signals.csv", delimiter=",", names=True)
        summaries.append({**summary, "signals": signals})
    return summaries


def test_stage_one_ends_where_the_yaw_rate_first_returns_to_zero(sweep) -> None:
    for s in sweep:
        signals, t = s["signals"], s["signals"]["time"]
        rate = signals["yaw_rate"]
        start = int(np.argmax(signals["open_1"] > 0.5))
        onset = start + int(np.argmax(np.abs(rate[start:]) > 0.01 * np.abs(rate).max()))
        end = onset + round(s["turn_time"] / (t[1] - t[0]))
        assert rate[end] <= 0.0 < rate[end - 1] and np.all(rate[onset:end] > 0.0)
        change = np.degrees(signals["yaw"][end] - signals["yaw"][start])
        assert s["heading_change"] == pytest.approx(change, rel=1e-9)
        assert s["turn_direction"] == "left"  # valve 1: yaw up


def test_the_turn_s_direction_is_in_the_summary(tmp_path: Path) -> None:
    """heading_change is a size; which way the fish turned is turn_direction (side 2: right,
    its final heading negative)."""
    path = scenario_file(
        tmp_path, "fish-escape", {"side": "side = 2", "duration": "duration = 0.3"}
    )
    s = run(path, tmp_path / "right")
    assert s["turn_direction"] == "right" and s["heading_change"] > 30.0
    assert s["final_heading"] < 0.0


def test_sweep_heading_change_rises_with_open_time_beyond_100_degrees(sweep) -> None:
    headings = [s["heading_change"] for s in sweep]
    assert all(b > a for a, b in zip(headings, headings[1:], strict=False)), headings
    assert headings[-1] > 100.0
    assert all(s["success"] and s["manoeuvres"] == 1 for s in sweep)


def test_sweep_accelerations_and_turn_times_are_biological(sweep) -> None:
    for s in sweep:
        assert 16.0 <= s["peak_acceleration"] <= 151.0
        assert 0.030 <= s["turn_time"] <= 0.210
    # a longer pulse turns further and so for longer
    times = [s["turn_time"] for s in sweep]
    assert all(b > a for a, b in zip(times, times[1:], strict=False))


def test_elastic_plus_resistive_work_never_exceeds_the_gas_work(sweep) -> None:
    for s in sweep:
        for m in s["work"]:
            assert m["gas_work"] > 0.0
            assert m["elastic"] + m["resistive"] <= m["gas_work"] + 1e-9
            # at the peak of the gas work the split closes (FishBody's energy balance)
            total = m["elastic"] + m["kinetic"] + m["resistive"]
            assert total == pytest.approx(m["gas_work"], rel=1e-4)
        assert s["work_violations"] == 0
    # more gas, more work, more gas used
    assert all(
        b["gas_used"] > a["gas_used"] and b["work"][0]["gas_work"] > a["work"][0]["gas_work"]
        for a, b in zip(sweep, sweep[1:], strict=False)
    )


def test_larger_nozzle_gives_a_higher_peak_yaw_rate(tmp_path: Path) -> None:
    rates = []
    for d in (1.2e-3, 1.8e-3):
        path = scenario_file(
            tmp_path, "fish-escape", {"open_time": f"open_time = 0.04\nd_nozzle = {d}"}
        )
        rates.append(run(path, tmp_path / f"d{d}")["peak_yaw_rate"])
    assert rates[1] > 1.1 * rates[0]


# ------------------------------------------------------------------ swimming and heading


def test_a_large_nozzle_escape_is_one_manoeuvre_below_the_supply(tmp_path: Path) -> None:
    # defect B: with a 2.5 mm nozzle the channel once overshot the supply, tripped the valve
    # driver's 300 kPa over-pressure vent, re-opened and counted the escape as two manoeuvres
    path = scenario_file(
        tmp_path, "fish-escape", {"open_time": "open_time = 0.06\nd_nozzle = 0.0025"}
    )
    summary = run(path, tmp_path / "out")
    assert summary["manoeuvres"] == 1 and summary["heading_change"] is not None
    signals = np.genfromtxt(tmp_path / "out" / "signals.csv", delimiter=",", names=True)
    assert np.all(signals["p_a"] <= signals["p_supply"] - 101325.0)
    assert np.all(np.diff(signals["m_vented"]) >= 0.0)
    assert np.all(signals["valve_state_2"] == CLOSED)  # never opened, never seen venting


def test_fish_swim_moves_forward(tmp_path: Path) -> None:
    path = scenario_file(tmp_path, "fish-swim", {"duration": "duration = 1.0"})
    s = run(path, tmp_path / "swim")
    assert s["forward_speed"] > 0.05 and s["forward_speed_bl"] > 0.1
    assert s["manoeuvres"] >= 3 and s["success"] and not s["gas_exhausted"]
    # the gas budget from the true canister mass: beyond the report's 8-bit 255 ("or more")
    assert s["manoeuvres_left_reported"] == 255 and s["manoeuvres_left"] > 255
    signals = np.genfromtxt(tmp_path / "swim" / "signals.csv", delimiter=",", names=True)
    reserve = json.loads((tmp_path / "swim" / "controller.json").read_text())["gas_reserve"]
    per = s["gas_used"] / s["manoeuvres"]
    usable = signals["m_canister"][-1] - reserve
    assert s["manoeuvres_left"] * per <= usable < (s["manoeuvres_left"] + 1) * per


def test_fish_heading_holds_within_10_degrees_with_the_realistic_camera(tmp_path: Path) -> None:
    path = resolve_scenario("fish-heading")
    scenario = load_scenario(path)
    assert scenario.camera.noise > 0 and scenario.camera.dropout > 0  # the realistic camera
    assert scenario.camera.outlier_rate > 0
    s = run(path, tmp_path / "heading")
    assert s["hold_start"] is not None and s["hold_start"] < 1.0
    assert s["heading_error_max"] <= 10.0 and s["success"]
    assert abs(s["final_heading"] - 60.0) <= 10.0


@pytest.mark.parametrize("seed", [2, 5, 6])
def test_fish_heading_holds_within_10_degrees_on_every_seed(tmp_path: Path, seed: int) -> None:
    """A short fish-heading on seeds whose camera noise once fooled the controller (5, 6: the
    yaw rate passing through zero at the first turn's overshoot read as the head at rest): the
    hold starts once the head has settled and the beat-averaged heading stays within 10 deg."""
    path = scenario_file(
        tmp_path, "fish-heading", {"seed": f"seed = {seed}", "duration": "duration = 1.0"}
    )
    s = run(path, tmp_path / "heading")
    assert s["status"] == "completed" and s["success"], s["heading_error_max"]
    assert 0.25 < s["hold_start"] < 0.6  # after the overshoot, before the run's end
    assert s["heading_error_max"] <= 10.0
    assert abs(s["final_heading"] - 60.0) <= 10.0


def test_running_the_canister_down_ends_in_a_clear_state(tmp_path: Path) -> None:
    path = scenario_file(
        tmp_path,
        "fish-swim",
        {"duration": "duration = 1.5", "duty": "duty = 0.6", "frequency": "frequency = 4.0"},
        "\n[robot.source]\nV_canister = 2e-6\nm_initial = 0.5e-3\n",
    )
    s = run(path, tmp_path / "empty")
    assert s["status"] == "completed" and s["gas_exhausted"] and not s["success"]
    assert "canister ran down" in s["end_reason"] and "reported no gas" in s["end_reason"]
    assert s["manoeuvres_left"] == 0
    signals = np.genfromtxt(tmp_path / "empty" / "signals.csv", delimiter=",", names=True)
    empty_at = signals["time"][np.argmax(signals["empty"] > 0.5)]
    no_gas = signals["mode"] == 6
    # once it has told, the controller stays in "no gas" and opens no valve any more
    told = int(np.argmax(no_gas))
    assert no_gas[told:-1].all() and signals["time"][told] <= empty_at + 0.01
    assert not signals["open_1"][told + 2 :].any() and not signals["open_2"][told + 2 :].any()


def test_same_seed_same_bytes_in_process_and_process_mode(tmp_path: Path) -> None:
    path = scenario_file(tmp_path, "fish-heading", {"duration": "duration = 0.2"})
    run(path, tmp_path / "a", inprocess=True)
    run(path, tmp_path / "b", inprocess=False)
    for name in ("can.log", "signals.csv"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


# ------------------------------------------------------------------ the pieces


def sync(cycle: int, ticks: int = 2, heartbeat: bool = False) -> SyncContext:
    return SyncContext(cycle, cycle * ticks, cycle * ticks * 1e-3, heartbeat)


def command(cycle: int, open_time: float, vent: int = 0) -> GenericFrame:
    signals = {"open_time": open_time, "vent": vent, "counter": (cycle - 1) % 256}
    return GenericFrame("ValveCommand", 1, signals)


def test_valve_driver_opens_for_exactly_the_commanded_ticks_and_vents_on_request() -> None:
    valve = ValveNode(1, 1e-3, 400e3, 300e3)
    inputs = {"opening": 0.0, "p_channel": 0.0, "p_supply": 400e3}
    valve.receive(command(1, 0.005))
    sent = valve.act(sync(1), inputs)
    assert sent[-1][1].signals["state"] == OPENING and valve.get_outputs()["open"] == 1.0
    opened = []
    for k in range(2, 10):  # the master steps it at ticks 2.. after the SYNC at tick 2
        valve.step(k * 1e-3, 1e-3)
        opened.append(valve.get_outputs()["open"])
    assert opened == [1.0] * 4 + [0.0] * 4  # ticks 2..6: five ticks open
    assert valve.pulses == 1
    assert valve.act(sync(4), {**inputs, "p_channel": 50e3})[-1][1].signals["state"] == VENTING
    assert valve.missed == 1  # SYNC 4 brought no command
    valve.receive(command(5, 0.5))
    assert valve.act(sync(5), {**inputs, "opening": 1.0})[-1][1].signals["state"] == OPEN
    valve.receive(command(6, 0.5, vent=1))  # vent aborts the pulse
    assert valve.act(sync(6), inputs)[-1][1].signals["state"] == CLOSED
    assert valve.get_outputs()["open"] == 0.0
    valve.receive(command(3, 0.5))  # an old counter: stale, not applied
    valve.act(sync(7), inputs)
    assert valve.stale == 1 and valve.get_outputs()["open"] == 0.0


def test_valve_driver_vents_an_over_pressure_and_flags_a_missing_supply() -> None:
    valve = ValveNode(2, 1e-3, 400e3, 100e3)
    valve.receive(GenericFrame("ValveCommand", 2, {"open_time": 0.5, "vent": 0, "counter": 0}))
    status = valve.act(sync(1), {"opening": 1.0, "p_channel": 120e3, "p_supply": 300e3})
    assert valve.get_outputs()["open"] == 0.0 and status[-1][1].signals["fault"] == 1 | 16


def test_controller_config_dispatches_on_the_robot(tmp_path: Path) -> None:
    config = controller_config(load_scenario(resolve_scenario("fish-escape")))
    assert isinstance(config, FishConfig) and config.open_time == 0.06
    assert read_config(config.to_json()) == config
    arm = controller_config(load_scenario(resolve_scenario("default")))
    assert type(read_config(arm.to_json())) is type(arm)
    bad = json.loads(config.to_json()) | {"robot": "snake"}
    with pytest.raises(ValueError, match="robot: 'snake' is not one of"):
        read_config(json.dumps(bad))
    with pytest.raises(ValueError, match="duty"):
        read_config(json.dumps(json.loads(config.to_json()) | {"duty": 0.0}))


def test_the_fish_controller_waits_for_a_jittered_cameras_latest_frame(tmp_path: Path) -> None:
    """The fish's config carries the camera's jitter bound as the arm's does, and a written
    one out of range is one line naming the key, for either robot."""
    scenario = load_scenario(resolve_scenario("fish-escape"))
    assert controller_config(scenario).camera_timing.delay_ticks == 0
    jittered = replace(scenario, camera=replace(scenario.camera, jitter=0.0005))
    config = controller_config(jittered)
    assert config.camera_timing.delay_ticks == 3  # ceil(6 x 0.5 ms / 1 ms)
    arm = controller_config(load_scenario(resolve_scenario("default")))
    for text in (config.to_json(), arm.to_json()):
        data = json.loads(text)
        data["camera_timing"]["delay_ticks"] = data["camera_timing"]["period_ticks"]
        with pytest.raises(ValueError, match=r"^camera_timing.delay_ticks: \d+ is outside 0"):
            read_config(json.dumps(data))


def test_calibration_is_monotonic_and_inverted_by_interpolation() -> None:
    times = [t for t, _ in CALIBRATION]
    angles = [a for _, a in CALIBRATION]
    assert all(b > a for a, b in zip(angles, angles[1:], strict=False))
    for t, a in CALIBRATION[1:-1]:
        assert open_time_for(CALIBRATION, a) == pytest.approx(t)
        assert open_time_for(CALIBRATION, -a) == pytest.approx(t)  # either side
    mid = 0.5 * (angles[4] + angles[5])
    assert times[4] < open_time_for(CALIBRATION, mid) < times[5]
    assert open_time_for(CALIBRATION, math.radians(500)) == times[-1]  # clamped


@pytest.mark.parametrize(
    ("replace", "extra", "key"),
    [
        ({"side": "side = 3"}, "", "robot.side"),
        ({"[robot]": "[robot]\nfrequency = 1000.0"}, "", "robot.frequency"),
        ({"[robot]": "[robot]\nfrequency = 125.1"}, "", "robot.frequency"),
        ({"open_time": "open_time = 2.0"}, "", "robot.valve.open_time"),
        ({}, "\n[robot.valve.3]\nd_nozzle = 1e-3\n", "robot.valve.3"),
        ({}, "\n[robot.body]\nx_start = 0.1\n", "robot.body.x_start"),
        ({"open_time": "open_time = 0.06\nd_nozzle = 0.02"}, "", "robot.valve.d_nozzle"),
        ({}, "\n[robot.valve.2]\nd_vent = 0.5\n", "robot.valve.2.d_vent"),
        ({'kind = "escape"': 'kind = "dance"'}, "", "task.kind"),
    ],
)
def test_scenario_errors_name_the_key(tmp_path: Path, replace, extra, key) -> None:
    text = resolve_scenario("fish-escape").read_text()
    for old, new in replace.items():
        text = re.sub(rf"(?m)^{re.escape(old)}( = .*)?$", new, text, count=1)
    path = tmp_path / "bad.toml"
    path.write_text(text + extra)
    with pytest.raises(ScenarioError) as error:
        load_scenario(path)
    message = str(error.value)
    assert f": {key}: " in message and "\n" not in message


def test_the_highest_beat_frequency_loads_and_errors_list_tasks_by_name(tmp_path: Path) -> None:
    """A half beat of exactly two control periods (2 ms: 125 Hz) is the limit, not refused; the
    unknown-task error lists the tasks as words, not a Python tuple."""
    text = resolve_scenario("fish-escape").read_text()
    path = tmp_path / "fast.toml"
    path.write_text(text.replace("[robot]", "[robot]\nfrequency = 125.0", 1))
    assert load_scenario(path).robot.frequency == 125.0
    path.write_text(text.replace('kind = "escape"', 'kind = "dance"'))
    with pytest.raises(ScenarioError, match=r"must be one of escape, swim, heading, got 'dance'$"):
        load_scenario(path)


def test_heading_hold_lengthens_the_strokes_that_turn_towards_the_reference() -> None:
    """In the hold, a heading below the reference (error > 0, turn left) lengthens valve 1's
    strokes (channel a turns the head left) and shortens valve 2's, and the reverse."""
    from rigbus.protocol import Protocol
    from robots.fish.controller import FishControl, FishEstimate

    config = controller_config(load_scenario(resolve_scenario("fish-heading")))
    vented = {
        ("ValveStatus", n): GenericFrame("ValveStatus", n, {"state": 0, "fault": 0}) for n in (1, 2)
    }
    strokes = {}
    for offset in (-0.1, 0.1):  # the fish points 0.1 rad right of / left of the reference
        control = FishControl(config, Protocol())
        control.turned, control.mode = True, 4  # after the first turn: holding
        control.mean_yaw = config.heading + offset
        estimate = FishEstimate(0.0, 0.0, config.heading + offset, 0.0, True)
        opened = []
        for cycle in range(300, 300 + round(1.0 / config.frequency / config.control_period)):
            t = cycle * config.control_period
            for frame in control.compute(cycle, t, estimate, vented):
                if frame.kind == "ValveCommand" and frame.signals["open_time"] > 0:
                    opened.append((frame.index, frame.signals["open_time"]))
        first = {n: max(o for i, o in opened if i == n) for n in (1, 2)}
        strokes[offset] = first
    assert strokes[-0.1][1] > strokes[-0.1][2]  # right of the reference: turn left (valve 1)
    assert strokes[0.1][2] > strokes[0.1][1]


@pytest.mark.parametrize("error_deg", [25.0, -25.0])
def test_a_corrective_stroke_turns_towards_the_reference_by_the_calibration(
    error_deg: float,
) -> None:
    """Beyond the deadband, the next stroke on the side that turns towards the reference is
    lengthened to the calibration's open time for the error; a stroke on the other side is not,
    and a correction waits a beat before the next."""
    from rigbus.protocol import Protocol
    from robots.fish.controller import FishControl

    config = controller_config(load_scenario(resolve_scenario("fish-heading")))
    error = math.radians(error_deg)
    towards = 0 if error > 0.0 else 1
    half = 0.5 / config.frequency
    plain = min(config.duty * half, 0.95 * half)
    wanted = min(open_time_for(config.calibration, error), 0.95 * half)
    assert wanted > plain  # a 25 degree correction needs a longer opening than a stroke
    for side in (towards, 1 - towards):
        control = FishControl(config, Protocol())
        at = config.start + 0.5
        control.next_stroke, control.stroke_side = at, side
        control._swim(at, {}, 0.0, error)
        opened = control.pulse_end[side] - at
        if side == towards:
            assert opened == pytest.approx(wanted) and control.corrected_at == at
        else:
            assert opened == pytest.approx(plain) and control.corrected_at == -math.inf


def test_only_the_heading_task_plots_a_heading_reference(tmp_path: Path) -> None:
    """The escape and the swim have no reference: a dashed line at 0 deg said they had."""
    from hil.rig import robot_kind

    fish = robot_kind("fish")
    for name, drawn in (("fish-escape", False), ("fish-swim", False), ("fish-heading", True)):
        scenario = load_scenario(scenario_file(tmp_path, name, {}))
        heading = next(p for p in fish.plots(scenario) if p.name == "heading")
        assert ("heading_ref" in [line[0] for line in heading.lines]) is drawn, name


def test_a_nozzle_beyond_the_lumped_channel_is_refused_with_its_range(tmp_path: Path) -> None:
    # defect C: 0.5 m once failed mid-run ("canister mass ... is not positive"), 0.02 m diverged
    path = scenario_file(tmp_path, "fish-escape", {"open_time": "open_time = 0.06\nd_nozzle = 0.5"})
    with pytest.raises(ScenarioError, match=r"robot\.valve\.d_nozzle: .*\[1e-06, 0\.005\]$"):
        load_scenario(path)


def test_a_swim_stroke_shorter_than_a_step_is_refused_naming_duty_and_frequency(
    tmp_path: Path,
) -> None:
    """frequency = 100 with duty 0.1 opened the valve 0.5 ms a stroke: the driver, opening for
    whole 1 ms steps, never opened it, and the fish-heading run reported success unmoved."""
    for name in ("fish-swim", "fish-heading"):
        path = scenario_file(
            tmp_path, name, {"frequency": "frequency = 100.0", "duty": "duty = 0.1"}
        )
        with pytest.raises(ScenarioError) as error:
            load_scenario(path)
        assert str(error.value).endswith(
            ": robot.duty: a stroke opens the valve for duty / (2 frequency) = 0.5 ms, less than "
            "one step of 1 ms, so no valve would open; raise robot.duty (got 0.1) or lower "
            "robot.frequency (got 100 Hz)"
        ), str(error.value)
        path = scenario_file(
            tmp_path, name, {"frequency": "frequency = 50.0", "duty": "duty = 0.1"}
        )
        assert load_scenario(path).robot.frequency == 50.0  # 1 ms: one step, the limit


@pytest.mark.parametrize(
    ("replace", "ending"),
    [
        ({"start": "start = 0.5"}, "robot.start: must be in [0, 0.4) s (the run), got 0.5"),
        ({"start": "start = 0.4"}, "robot.start: must be in [0, 0.4) s (the run), got 0.4"),
        ({"side": "side = 1\nturn_angle = 500.0"}, "(the calibration), got 500"),
        (
            {"side": "side = 1\nheading = 200.0"},
            "robot.heading: must be in [-180, 180] deg, got 200",
        ),
    ],
)
def test_task_key_errors_give_the_range_and_the_value(
    tmp_path: Path, replace: dict[str, str], ending: str
) -> None:
    with pytest.raises(ScenarioError) as error:
        load_scenario(scenario_file(tmp_path, "fish-escape", replace))
    assert str(error.value).endswith(ending), str(error.value)


def test_a_fish_that_leaves_the_camera_s_view_before_its_hold_is_a_warning(
    tmp_path: Path,
) -> None:
    """heading = -60 from the default start swims the nose out of the camera's view before
    the hold: the run is scored from the true signals, and says the controller was blind."""
    path = scenario_file(
        tmp_path, "fish-heading", {"heading": "heading = -60.0", "duration": "duration = 0.6"}
    )
    s = run(path, tmp_path / "blind")
    left = s["nose_out_of_view_at"]
    assert left is not None and left < s["hold_start"]
    assert s["warnings"] == [
        f"the nose left the camera's view at t = {left:.3f} s, before the hold "
        f"({s['hold_start']:.3f} s): the controller glided without a heading estimate; the "
        "heading is scored from the true signals"
    ]
    signals = np.genfromtxt(tmp_path / "blind" / "signals.csv", delimiter=",", names=True)
    nose = np.abs(np.c_[signals["nose_x"], signals["nose_y"]]).max(axis=1)
    k = int(np.argmax(signals["time"] >= left))
    assert nose[k] > 0.55 and nose[:k].max() <= nose[k]  # the first sample out of view


def test_after_a_turn_the_strokes_resume_on_the_other_side_from_where_the_head_rests() -> None:
    """Vented and at rest for `settle_time` after a turn on side a, the hold starts: the beat
    average starts again at the resting yaw (not the yaw averaged through the turn), and the
    first stroke is on side b at once, sized by that heading's error."""
    from rigbus.protocol import Protocol
    from robots.fish.controller import HOLD, TURN, FishControl, FishEstimate, wrap

    config = controller_config(load_scenario(resolve_scenario("fish-heading")))
    T = config.control_period
    vented = {
        ("ValveStatus", n): GenericFrame("ValveStatus", n, {"state": 0, "fault": 0}) for n in (1, 2)
    }
    control = FishControl(config, Protocol())
    first = 300
    control.turned, control.mode, control.stroke_side = True, TURN, 0
    control.pulse_end = [first * T + T, 0.0]  # the turn's pulse on side a ends at the first SYNC
    control.mean_yaw = config.heading - 0.5  # averaged through the turn
    rests = config.heading + 0.1
    estimate = FishEstimate(0.0, 0.0, rests, 0.0, True)
    for cycle in range(first, first + round(config.settle_max / T)):
        frames = control.compute(cycle, cycle * T, estimate, vented)
        opened = [f for f in frames if f.kind == "ValveCommand" and f.signals["open_time"] > 0]
        if opened:
            break
    assert control.mode == HOLD and control.mean_yaw == rests
    assert cycle * T + T - (first * T + T) == pytest.approx(config.settle_time, abs=1.5 * T)
    half = 0.5 / config.frequency
    bias = max(-1.0, min(1.0, config.heading_gain * wrap(config.heading - rests)))
    assert [f.index for f in opened] == [2]
    expected = min(config.duty * half * (1.0 - bias), 0.95 * half)
    assert opened[0].signals["open_time"] == pytest.approx(expected, abs=1e-4)


def test_corrective_strokes_are_a_beat_apart_whichever_side_they_turn() -> None:
    """A correction waits a beat after the last (the beat-averaged heading has seen it before
    the next is sized), even when the error has changed sign and the next stroke, half a beat
    later, is on the side that now turns towards the reference."""
    from rigbus.protocol import Protocol
    from robots.fish.controller import FishControl

    config = controller_config(load_scenario(resolve_scenario("fish-heading")))
    half = 0.5 / config.frequency
    error = math.radians(25.0)
    control = FishControl(config, Protocol())
    at = config.start + 0.5
    control.next_stroke, control.stroke_side = at, 0
    control._hold_heading(at, half, config.heading - error, {})  # right of it: turn left (a)
    assert control.corrected_at == at
    later = control.next_stroke
    assert later == pytest.approx(at + half) and control.stroke_side == 1
    control._hold_heading(later, half, config.heading + error, {})  # left of it now: b turns
    assert control.corrected_at == at
    bias = max(-1.0, min(1.0, -config.heading_gain * error))
    plain = min(config.duty * half * (1.0 - bias), 0.95 * half)
    assert control.pulse_end[1] - later == pytest.approx(plain)
