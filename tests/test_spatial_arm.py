"""The spatial arm as a robot kind: its closed loop end to end (tip positioning, an object found
by the camera, shape fitting, configuration control), determinism in-process and across
processes, and the pieces: the C markers against the numpy kinematics, the trapezoidal move,
the drive numbering and wiring, the 3-D camera frames on both sides, the estimator's filter, the
metrics' windows, the scenario's one-line errors and `hil envelope`."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from controllers.estimation import MarkerFrame
from controllers.node import CameraAssembler
from hil.cli import main
from hil.scenario import ScenarioError, load_scenario
from rigbus.protocol import CameraFrame, CameraMarker, CameraMarker3D, Protocol
from robots.spatial_arm.controller import kinematics
from robots.spatial_arm.controller.config import SpatialConfig
from robots.spatial_arm.controller.control import Trapezoid
from robots.spatial_arm.controller.markers import Markers, load
from robots.spatial_arm.controller.model import ArmModel
from robots.spatial_arm.plant import metrics
from robots.spatial_arm.plant.rig import drive_of, wiring
from robots.spatial_arm.plant.signals import axis_of
from tests.helpers import run_summary as run
from tests.helpers import scenario_variant as scenario_file

# ------------------------------------------------------------------ the closed loop


@pytest.fixture(scope="module")
def point_runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    """Two goals of spatial-point in-process and with the controller in its own process."""
    folder = tmp_path_factory.mktemp("spatial")
    path = scenario_file(
        folder, "spatial-point", {"count": "count = 2", "duration": "duration = 8.0"}
    )
    inprocess, process = folder / "in", folder / "process"
    summary = run(path, inprocess)
    run(path, process, inprocess=False)
    return inprocess, process, summary


def test_point_goals_are_reached_within_the_camera_noise(point_runs: tuple) -> None:
    """Both goals settle with the true tip within 2 mm (the realistic camera's markers carry
    0.5 mm of noise; the estimate fuses five markers a picture); the droop is gravity's."""
    _, _, s = point_runs
    assert s["targets"] == 2 and s["targets_settled"] == 2 and s["success"] is True
    assert s["tip_error_max"] < 2e-3
    assert s["time_to_settle"] < 4.0
    assert s["droop"] == pytest.approx(0.2794, abs=1e-4)  # as ArmBody's calibration


def test_same_seed_same_bytes_in_process_and_across_processes(point_runs: tuple) -> None:
    inprocess, process, _ = point_runs
    for name in ("can.log", "signals.csv"):
        assert (inprocess / name).read_bytes() == (process / name).read_bytes(), name


def test_the_can_log_holds_3d_markers_and_the_task_state(point_runs: tuple) -> None:
    inprocess, _, _ = point_runs
    ids = {
        line.split()[2].split("#")[0] for line in (inprocess / "can.log").read_text().splitlines()
    }
    assert f"{0x290:03X}" in ids and f"{0x294:03X}" in ids  # markers 0 (base) and 4 (tip)
    assert f"{0x3F2:03X}" in ids  # SpatialTaskState
    assert f"{0x188:03X}" in ids  # drive 8: segment 4's y pair


@pytest.mark.parametrize(
    ("name", "key", "limit"),
    [("spatial-object", "tip_error_max", 2e-3), ("spatial-shape", "shape_error_max", 2e-3)],
)
def test_object_and_shape_tasks(tmp_path: Path, name: str, key: str, limit: float) -> None:
    path = scenario_file(tmp_path, name, {"duration": "duration = 5.0"})
    s = run(path, tmp_path / "run")
    assert s[key] < limit


def test_configuration_steps_are_tracked(tmp_path: Path) -> None:
    """Bend steps drawn among the static rests: each coordinate ends within 0.02 rad."""
    path = scenario_file(
        tmp_path,
        "spatial-point",
        {"count": "count = 1", "duration": "duration = 4.0"},
    )
    path.write_text(path.read_text().replace('kind = "point"', 'kind = "configuration"'))
    s = run(path, tmp_path / "run")
    assert s["steps"] == 1 and s["steps_pursued"] == 1
    assert s["bend_error_max"] < 0.02


# ------------------------------------------------------------------ the pieces


def test_c_markers_equal_the_numpy_kinematics() -> None:
    """The loop's C markers and complex-step Jacobian against kinematics' analytic ones, at
    zero bend, tiny bends, the series' switch-over (|W| = 1) and random bends."""
    if load() is None:
        pytest.skip("the C markers did not build")
    model = ArmModel.from_fmu_parameters({})
    fast = Markers(model)
    rng = np.random.default_rng(3)
    cases = [np.zeros(8), np.full(8, 1e-9), np.array([0.6, 0.8, 1.0, 0, 0, 1.0, -0.7071, 0.7071])]
    cases += list(rng.uniform(-1.2, 1.2, (10, 8)))
    for q in cases:
        m, J = fast(q)
        m_ref, J_ref = kinematics.marker_jacobian(model, q)
        assert np.max(np.abs(m - m_ref)) < 1e-14
        assert np.max(np.abs(J - J_ref)) < 1e-12


def test_a_trapezoid_reaches_the_speed_and_the_goal() -> None:
    q0, q1 = np.zeros(2), np.array([1.0, -0.5])
    move = Trapezoid.plan(2.0, q0, q1, speed=0.5, acceleration=1.0)
    # accelerate 0.5 s (0.125 rad), cruise 1.5 s, decelerate 0.5 s: 2.5 s for 1 rad
    assert move.t_acc == pytest.approx(0.5) and move.t_total == pytest.approx(2.5)
    assert move.share(2.0) == 0.0 and move.share(4.5) == 1.0
    assert np.allclose(move.at(2.0 + 0.5), q0 + 0.125 * (q1 - q0))
    rate = (move.at(3.5 + 1e-6) - move.at(3.5 - 1e-6)) / 2e-6
    assert rate[0] == pytest.approx(0.5, rel=1e-6)  # the coordinate that moves most
    assert rate[1] == pytest.approx(-0.25, rel=1e-6)
    short = Trapezoid.plan(0.0, q0, np.array([0.04, 0.0]), speed=0.5, acceleration=1.0)
    assert short.t_total == pytest.approx(0.4)  # triangular: 2 sqrt(0.04 / 1)


def test_drive_numbering_and_wiring() -> None:
    assert [drive_of(i, a) for i in (1, 2) for a in "xy"] == [1, 2, 3, 4]
    assert [axis_of(n) for n in (1, 2, 3, 8)] == [(1, "x"), (1, "y"), (2, "x"), (4, "y")]
    links = dict((target, source) for source, target in wiring(2))
    assert links["body.x_piston_x_2"] == "cylinder3.x"
    assert links["body.x_piston_y_2"] == "cylinder4.x"
    assert links["cylinder4.p_a"] == "body.p_a_y_2"
    assert links["drive1.p_b"] == "body.p_b_x_1"
    assert links["camera.tip_z_2"] == "body.tip_z_2"


def test_the_controller_assembles_3d_pictures() -> None:
    camera = CameraAssembler(3, dims=3)
    camera.add(CameraFrame(7, 0.004, 0b101, 2))
    camera.add(CameraMarker3D(0, 7, 0.0, 0.0, 0.0))
    assert not camera.complete(7)
    camera.add(CameraMarker(2, 0.5, 0.5, 7, 0.0))  # a planar marker is not this camera's
    assert not camera.complete(7)
    camera.add(CameraMarker3D(2, 7, 0.1, -0.2, 0.3))
    assert camera.complete(7)
    frame = camera.take(7, 1.0)
    assert frame.exposure_time == pytest.approx(0.996)
    assert frame.points.shape == (3, 3)
    assert np.isnan(frame.points[1]).all()
    assert list(frame.points[2]) == [0.1, -0.2, 0.3]


def test_the_plant_camera_sends_3d_marker_frames(tmp_path: Path) -> None:
    from hil.devices import CameraNode, SyncContext
    from hil.vision import Camera, CameraEffects

    camera = Camera(CameraEffects(), np.random.default_rng(0), 0.02, 0.001)
    node = CameraNode(["a"], lambda v: np.array([[0.0, 0.0, 0.0], [0.1, 0.2, -0.7]]), 0,
                      camera, dims=3)  # fmt: skip
    node.step(0.0, 0.001)
    frames = [f for _, f in node.act(SyncContext(0, 0, 0.0), {})]
    header, marker = frames[0], frames[1:]
    assert header.marker_mask == 0b01  # z -0.7 m is beyond the DBC's 0.6 m: not seen
    assert [type(m) for m in marker] == [CameraMarker3D]
    Protocol().encode(marker[0])


def test_the_estimator_converges_on_noiseless_markers() -> None:
    """The arm at rest at a bent shape, the drives reporting the pistons that hold it there:
    the filter's prediction (the equilibrium those pistons hold under gravity) and the pictures
    agree, and the estimate converges on the truth from the straight start."""
    from controllers.estimation import DriveReading
    from robots.spatial_arm.controller import statics
    from robots.spatial_arm.controller.estimator import SpatialEstimator

    model = ArmModel.from_fmu_parameters({})
    estimator = SpatialEstimator(_config(model, np.zeros(8)), model)
    truth = np.array([-0.3, -0.1, -0.2, 0.15, -0.2, 0.1, 0.05, -0.3])
    pistons = statics.pistons_for(model, truth).x
    assert np.all(np.isfinite(pistons))
    drives = {n + 1: DriveReading(float(x), 0.0, 0.0) for n, x in enumerate(pistons)}
    points = kinematics.markers(model, truth)
    estimate = None
    for k in range(1, 200):
        t = 0.02 * k
        estimate = estimator.update(t, drives, [MarkerFrame(t, points)])
    assert estimate is not None
    assert np.max(np.abs(estimate.q - truth)) < 1e-5
    assert np.max(np.abs(estimate.q_rate)) < 1e-4
    assert np.linalg.norm(estimate.tip - points[-1]) < 1e-6
    # the prediction alone: the equilibrium the reported pistons hold is the truth
    assert np.max(np.abs(estimate.equilibrium - truth)) < 1e-4


def test_the_estimator_gates_an_outlier() -> None:
    from robots.spatial_arm.controller.equilibrium import static_equilibrium
    from robots.spatial_arm.controller.estimator import SpatialEstimator

    model = ArmModel.from_fmu_parameters({})
    # at rest where the sealed pistons hold the arm: prediction and pictures agree
    start = static_equilibrium(model, np.full(8, model.x_seal)).q
    estimator = SpatialEstimator(_config(model, start), model)
    points = kinematics.markers(model, start)
    for k in range(1, 20):
        estimator.update(0.02 * k, {}, [MarkerFrame(0.02 * k, points)])
    wild = points.copy()
    wild[2] += [0.05, 0.0, 0.0]  # a 5 cm outlier on marker 2
    estimate = estimator.update(0.4, {}, [MarkerFrame(0.4, wild)])
    assert estimate.gated == 1 and estimate.measured == 3
    assert np.max(np.abs(estimate.q - start)) < 1e-3


def _config(model: ArmModel, start: np.ndarray) -> SpatialConfig:
    from controllers.config import CameraTiming

    return SpatialConfig(
        robot="spatial_arm",
        control_period=0.02,
        cycles=10,
        camera_timing=CameraTiming(20, 10, 20, 5, dims=3),
        segments=4,
        body=tuple(sorted(model.to_fmu_parameters().items())),
        start=tuple(map(float, start)),
        camera_noise=3e-4,
    )


def test_the_config_round_trips_and_names_bad_keys() -> None:
    model = ArmModel.from_fmu_parameters({})
    config = _config(model, np.zeros(8))
    assert SpatialConfig.from_json(config.to_json()) == config
    data = json.loads(config.to_json())
    data["start"] = [0.0] * 7
    with pytest.raises(ValueError, match="start: needs 8 bends, got 7"):
        SpatialConfig.from_json(json.dumps(data))


def test_metrics_windows_and_settling() -> None:
    signals = {
        "target_index": np.array([0, 0, 0, 0, 1, 1, 1, 2, 2], dtype=float),
        "phase": np.array([0, 1, 2, 3, 1, 2, 3, 4, 4], dtype=float),
    }
    assert metrics.windows(signals) == [(0, 1, 3), (1, 4, 6)]
    t = np.arange(6) * 0.5
    distance = np.array([0.02, 0.001, 0.006, 0.001, 0.0005, 0.0001])
    # within 5 mm for good from t = 1.5 s: 1.5 s after the window's start
    assert metrics.settle_time(t, distance, 0, 5, 0.005) == pytest.approx(1.5)
    assert metrics.settle_time(t, distance[::-1], 0, 5, 0.005) is None
    line = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert metrics.point_to_polyline(np.array([0.3, 0.4, 0.5]), line) == pytest.approx(0.5)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ("[robot.body]\ng_x = 1.0\n", "robot.body.g_x: robot.segments, robot.pose"),
        ("[robot.body]\nk_1 = -1.0\n", "robot.body.k_1: -1 is outside the allowed range"),
        ("[robot.cylinder]\nbore = 0.02\n", "robot.cylinder.bore: the body's bore"),
    ],
)
def test_bad_tables_get_one_line(tmp_path: Path, extra: str, message: str) -> None:
    path = scenario_file(tmp_path, "spatial-point", {}, "\n" + extra)
    with pytest.raises(ScenarioError, match=re.escape(message)):
        load_scenario(path)


def test_goals_beyond_the_reach_are_refused(tmp_path: Path) -> None:
    path = scenario_file(
        tmp_path, "spatial-point", {"pose": 'pose = "horizontal"\ngoals = [[0.0, 0.0, 0.6]]'}
    )
    with pytest.raises(ScenarioError, match=r"robot.goals\[0\]: .* beyond the arm's reach"):
        load_scenario(path)


def test_hil_envelope_writes_and_reports(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "env"
    assert main(["envelope", "spatial-point", "--samples", "200", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "passive droop 279.4 mm below the straight tip" in text
    tips = np.loadtxt(out / "envelope.csv", delimiter=",", skiprows=1)
    stored = np.load(out / "envelope.npz")
    assert tips.shape[1] == 3 and np.array_equal(tips, stored["points"])
    model = ArmModel.from_fmu_parameters({})
    # every exported tip is the tip of its exported bends
    assert np.allclose(kinematics.tip(model, stored["q"]), tips, atol=1e-12)
    assert (out / "envelope.png").stat().st_size > 10_000
    assert main(["envelope", "default", "--out", str(tmp_path / "x")]) == 1
    assert "has no statically reachable envelope" in capsys.readouterr().err


def test_radians_per_metre_in_the_state_frames() -> None:
    """ControllerState carries a bend as curvature theta / L: the DBC's +-30 1/m holds a
    coordinate of the 0.09 m tip segment up to 2.7 rad, beyond the 1.6 rad limit."""
    lo, hi = Protocol().signal_range("ControllerState8", "kappa_ref")
    assert hi * 0.09 > 1.6 and math.isclose(lo, -hi)
