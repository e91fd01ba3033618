"""The spatial arm's pieces pinned one by one, where the closed-loop runs of test_spatial_arm.py
are blind to a deliberate bug (a mutation run found them): every pair's wiring, the trapezoid's
deceleration, the filter's measurement variance and its gate's threshold, the drives' damping
of the slow modes, the anti-windup, the task-space correction's direction, the metrics' windows
and their judgement of a settled goal, the confined plan's inside constraint and approach line,
the 3-D marker frames' fields, a planar camera refusing 3-D markers, the scenario checks,
`hil envelope --samples` and the drawn goals' piston band. Unit tests of the pieces: no run."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controllers.estimation import MarkerFrame
from controllers.node import CameraAssembler
from hil.cli import main
from hil.scenario import ScenarioError, load_scenario, resolve_scenario
from rigbus.protocol import (
    CameraFrame,
    CameraMarker,
    CameraMarker3D,
    DriveCommand,
    Protocol,
)
from robots.spatial_arm.controller import confined, dynamics, kinematics, statics
from robots.spatial_arm.controller.control import (
    DAMPED_BELOW,
    DAMPING_RATIO,
    TASK_GAIN,
    SpatialControl,
    Trapezoid,
)
from robots.spatial_arm.controller.equilibrium import static_equilibrium
from robots.spatial_arm.controller.estimator import GATE_CHI2, SpatialEstimate, SpatialEstimator
from robots.spatial_arm.controller.model import ArmModel
from robots.spatial_arm.plant import metrics, task
from robots.spatial_arm.plant.rig import SpatialArm, drive_of, wiring
from robots.spatial_arm.plant.signals import axis_of
from tests.test_spatial_arm import _config, scenario_file

NOISE = 3e-4  # [m] the camera noise of _config


@pytest.fixture(scope="module")
def model() -> ArmModel:
    return ArmModel.from_fmu_parameters({})


@pytest.fixture(scope="module")
def rest(model: ArmModel) -> np.ndarray:
    """The passive rest under gravity: every piston at its sealing position."""
    return np.asarray(static_equilibrium(model, np.full(model.n_q, model.x_seal)).q)


# ------------------------------------------------------------------ the rig's wiring


def test_every_pair_is_wired_to_its_own_drive_cylinder_and_sides() -> None:
    """Segment i's axis pair: its piston from cylinder n = drive_of(i, axis), the cylinder's and
    the drive's side a and side b from the body's same sides of that pair."""
    links = dict((target, source) for source, target in wiring(4))
    assert len(links) == len(wiring(4))  # no input driven twice
    assert sorted(drive_of(i, a) for i in range(1, 5) for a in "xy") == list(range(1, 9))
    for i in range(1, 5):
        for axis in "xy":
            n = drive_of(i, axis)
            assert axis_of(n) == (i, axis)
            assert links[f"body.x_piston_{axis}_{i}"] == f"cylinder{n}.x"
            assert links[f"drive{n}.x"] == f"cylinder{n}.x"
            assert links[f"cylinder{n}.x_ref"] == f"drive{n}.x_ref"
            assert links[f"cylinder{n}.enable"] == f"drive{n}.enable"
            assert links[f"drive{n}.servo_fault"] == f"cylinder{n}.fault"
            for side in ("p_a", "p_b"):
                assert links[f"cylinder{n}.{side}"] == f"body.{side}_{axis}_{i}"
                assert links[f"drive{n}.{side}"] == f"body.{side}_{axis}_{i}"


# ------------------------------------------------------------------ the trapezoid


def test_a_trapezoid_decelerates_as_it_accelerated() -> None:
    """The profile is symmetric in time (share(end - s) = 1 - share(start + s)); 0.25 s before
    the end, decelerating at 1 rad/s^2, the coordinate that moves most is at 0.25 rad/s; the
    rate is continuous where the cruise ends."""
    q0, q1 = np.zeros(2), np.array([1.0, -0.5])
    move = Trapezoid.plan(2.0, q0, q1, speed=0.5, acceleration=1.0)
    for s in np.linspace(0.0, move.t_total, 26):
        assert move.share(4.5 - s) == pytest.approx(1.0 - move.share(2.0 + s), abs=1e-12)

    def rate(t: float) -> float:
        h = 1e-7
        return float((move.at(t + h) - move.at(t - h))[0] / (2 * h))

    assert rate(4.25) == pytest.approx(0.25, rel=1e-5)
    assert rate(4.0 - 1e-6) == pytest.approx(rate(4.0 + 1e-6), abs=1e-5)
    assert move.share(4.0) == pytest.approx(1.0 - 0.125, abs=1e-12)  # 0.125 rad still to go


# ------------------------------------------------------------------ the estimator


def test_a_picture_updates_the_filter_with_the_cameras_variance(
    model: ArmModel, rest: np.ndarray
) -> None:
    """One picture of every endplate at t = 0 (no prediction before it): the bends' posterior
    covariance is (P0^-1 + J^T J / sigma^2)^-1, sigma the camera's noise, J the endplates'
    Jacobian (every marker but the base's)."""
    estimator = SpatialEstimator(_config(model, rest), model)
    P0 = np.array(estimator.filter.P[: model.n_q, : model.n_q])
    points = kinematics.markers(model, rest)
    estimate = estimator.update(0.0, {}, [MarkerFrame(0.0, points)])
    assert estimate.measured == 4 and estimate.gated == 0
    J = kinematics.marker_jacobian(model, rest)[1][1:].reshape(-1, model.n_q)
    P = np.linalg.inv(np.linalg.inv(P0) + J.T @ J / NOISE**2)
    assert np.allclose(estimate.q_std, np.sqrt(np.diag(P)), rtol=1e-6, atol=0.0)
    assert np.max(np.abs(estimate.q - rest)) < 1e-12  # the picture is the prediction


@pytest.mark.parametrize(("chi2", "gated"), [(25.0, 0), (36.0, 1)])
def test_the_gate_is_chi_square_30_on_the_predicted_spread(
    model: ArmModel, rest: np.ndarray, chi2: float, gated: int
) -> None:
    """Marker 2 moved along its innovation spread's narrowest direction (there the camera's
    variance and the prior's are alike): a Mahalanobis distance squared of 25 passes, 36 is an
    outlier."""
    assert GATE_CHI2 == 30.0
    estimator = SpatialEstimator(_config(model, rest), model)
    P0 = np.array(estimator.filter.P[: model.n_q, : model.n_q])
    J = kinematics.marker_jacobian(model, rest)[1][2]
    S = J @ P0 @ J.T + NOISE**2 * np.eye(3)
    lam, vectors = np.linalg.eigh(S)
    assert lam[0] < 2.0 * NOISE**2  # the camera's variance counts there
    wild = kinematics.markers(model, rest)
    wild[2] += math.sqrt(chi2 * lam[0]) * vectors[:, 0]
    estimate = estimator.update(0.0, {}, [MarkerFrame(0.0, wild)])
    assert (estimate.gated, estimate.measured) == (gated, 4 - gated)


# ------------------------------------------------------------------ the controller


def _estimate(model: ArmModel, q: np.ndarray, rate: np.ndarray | None = None) -> SpatialEstimate:
    zero = np.zeros(model.n_q)
    return SpatialEstimate(
        q=q,
        q_rate=zero if rate is None else rate,
        q_std=zero,
        markers=kinematics.markers(model, q),
        object=np.full(3, math.nan),
        object_frames=0,
        equilibrium=q,
    )


def _setpoints(frames: list[Any]) -> np.ndarray:
    return np.array([f.piston_setpoint for f in frames if isinstance(f, DriveCommand)])


def test_modal_damping_gives_the_slow_modes_their_ratio(model: ArmModel, rest: np.ndarray) -> None:
    """In the modal coordinates (mass-normalised) the damping is diag(2 zeta omega) on the modes
    below DAMPED_BELOW (the two first, near 1.2 Hz at the rest) and zero on the faster."""
    x = np.full(model.n_q, model.x_seal)
    M, H = dynamics.mass_matrix(model, rest), statics.stiffness(model, rest, x)
    omega, shapes = dynamics.modes(M, H)
    below = 2.0 * math.pi * DAMPED_BELOW
    assert list(omega < below) == [True, True] + [False] * 6
    assert omega[0] / (2.0 * math.pi) == pytest.approx(1.2, abs=0.1)
    C = dynamics.modal_damping(M, H, DAMPING_RATIO, below)
    expected = np.diag(np.where(omega < below, 2.0 * DAMPING_RATIO * omega, 0.0))
    assert np.allclose(shapes.T @ C @ shapes, expected, atol=1e-9 * omega[-1])


def test_the_drives_damp_the_bend_rates(model: ArmModel, rest: np.ndarray) -> None:
    """At the reference, a bend rate moves the setpoints by -damping @ rate: the pistons' torque
    on the bends (dtau/dx times the change) draws power from the motion."""
    control = SpatialControl(_config(model, rest), model, Protocol())
    still = _setpoints(control.command(0, _estimate(model, rest), {}))
    assert np.allclose(still, model.x_seal)  # the feedforward alone: the sealed pistons
    rate = np.random.default_rng(5).normal(0.0, 0.2, model.n_q)
    moving = _setpoints(control.command(1, _estimate(model, rest, rate), {}))
    assert np.allclose(moving - still, -control.damping @ rate, rtol=1e-12, atol=1e-15)
    d_x = statics.gas_torque(model, rest, still).d_x
    assert np.all(d_x > 0.0)  # advancing a pair's piston bends it towards its axis
    assert float(rate @ (d_x * (moving - still))) < 0.0


def test_the_integral_does_not_wind_up_on_a_saturated_stroke(
    model: ArmModel, rest: np.ndarray
) -> None:
    """With a PI (kp, ki set in controller.json): a large bend error saturates some pistons;
    their coordinates' integrals stay, the others' grow by error * period."""
    from dataclasses import replace

    config = replace(_config(model, rest), kp=1.0, ki=2.0)
    control = SpatialControl(config, model, Protocol())
    error = np.zeros(model.n_q)
    error[0], error[5] = 0.8, 0.01
    control.q_ref = rest + error
    setpoints = _setpoints(control.command(0, _estimate(model, rest), {}))
    saturated = (setpoints <= config.x_min) | (setpoints >= config.x_max)
    assert saturated[0] and not saturated[5]
    expected = np.where(saturated, 0.0, error * config.control_period)
    assert np.array_equal(control.integral, expected)


def test_the_task_space_correction_moves_the_tip_towards_the_target(
    model: ArmModel, rest: np.ndarray
) -> None:
    """In settling, a cycle moves the bend target so that its tip goes TASK_GAIN * period of
    the way to the target (the damped pseudo-inverse: to first order)."""
    control = SpatialControl(_config(model, rest), model, Protocol())
    control.q_goal = rest.copy()
    tip = kinematics.tip(model, rest)
    error = np.array([1e-3, -5e-4, 5e-4])
    control.target = tip + error
    x_before = control.x_goal.copy()
    control._task_space(_estimate(model, rest))
    moved = kinematics.tip(model, control.q_goal) - tip
    share = TASK_GAIN * 0.02  # 1 % of the error per 20 ms cycle
    assert np.allclose(moved, share * error, rtol=0.0, atol=0.01 * share * 1e-3)
    # the feedforward's pistons follow the bend target through the static inverse's slope
    assert np.allclose(control.x_goal - x_before, control.gain @ (control.q_goal - rest))


# ------------------------------------------------------------------ the metrics


def test_a_window_ends_when_the_controller_is_done() -> None:
    signals = {
        "target_index": np.array([0, 0, 0, 0, 0, 0], dtype=float),
        "phase": np.array([0, 1, 2, 3, 4, 4], dtype=float),
    }
    assert metrics.windows(signals) == [(0, 1, 3)]


def test_a_goal_counts_settled_within_the_tolerance_and_3_sigma(tmp_path: Path) -> None:
    """Two goals, each declared settled with the true tip a hair inside and a hair outside the
    tolerance plus 3 sigma of the camera's noise (3.5 mm): one counts; the run succeeds only
    with all of them settled."""
    goals = 'pose = "horizontal"\ngoals = [[0.0, 0.0, 0.3], [0.0, 0.1, 0.3]]'
    scenario = load_scenario(scenario_file(tmp_path, "spatial-point", {"pose": goals}))
    judged = scenario.task.tolerance + 3.0 * scenario.camera.noise
    assert judged == pytest.approx(3.5e-3)

    def run(errors: tuple[float, float]) -> dict[str, Any]:
        goals = np.array(scenario.robot.goals)
        tips = []
        for goal, e in zip(goals, errors, strict=True):
            tips += [goal + [0.0, 0.0, 0.02]] * 3 + [goal + [e, 0.0, 0.0]] * 2
        tip = np.array(tips)
        signals = {
            "time": 0.1 * np.arange(len(tip)),
            "target_index": np.repeat([0.0, 1.0], 5),
            "phase": np.tile([1.0, 2.0, 2.0, 2.0, 3.0], 2),
            **{f"tip_{c}_4": tip[:, k] for k, c in enumerate("xyz")},
        }
        return metrics.task_metrics(SpatialArm(), scenario, signals)

    inside, outside = judged - 1e-5, judged + 1e-5
    s = run((inside, outside))
    assert s["targets_settled"] == 1 and s["success"] is False
    assert s["tip_error_max"] == pytest.approx(outside)
    assert s["time_to_settle"] == pytest.approx(0.3)  # the 5 mm band entered at the 4th sample
    s = run((inside, inside))
    assert s["targets_settled"] == 2 and s["success"] is True


# ------------------------------------------------------------------ the confined plan


def test_the_inside_constraint_is_the_room_left_from_the_axis(model: ArmModel) -> None:
    """The straight arm along +z, the pipe's axis parallel to it 4 mm aside: every chosen
    station leaves room - 4 mm (positive: inside); the Jacobian is its derivative."""
    where = confined.arm_stations(model)
    pipe = confined.Pipe(np.array([[0.004, 0.0, 0.0], [0.004, 0.0, 1.0]]), 0.03)
    past = where.arc_length >= 0.2
    constraint = confined._inside_constraint(model, pipe, 0.01, where, past)
    assert constraint["type"] == "ineq"
    values = constraint["fun"](np.zeros(model.n_q))
    assert values.shape == (int(past.sum()),)
    assert np.allclose(values, 0.01 - 0.004, atol=1e-12)
    q = np.random.default_rng(2).uniform(-0.05, 0.05, model.n_q)
    h = 1e-6
    numeric = np.column_stack(
        [
            (constraint["fun"](q + h * e) - constraint["fun"](q - h * e)) / (2 * h)
            for e in np.eye(model.n_q)
        ]
    )
    assert np.allclose(constraint["jac"](q), numeric, atol=1e-5)


def test_the_pipe_measures_along_its_axis_and_before_its_entrance() -> None:
    pipe = confined.Pipe(np.array([[0.0, 0.0, 0.3], [0.0, 0.0, 0.4], [0.1, 0.0, 0.4]]), 0.03)
    assert pipe.length == pytest.approx(0.2)
    assert np.allclose(pipe.along(-0.06), [0.0, 0.0, 0.24])  # on the line before the entrance
    assert np.allclose(pipe.along(0.05), [0.0, 0.0, 0.35])
    assert np.allclose(pipe.along(0.15), [0.05, 0.0, 0.4])
    assert float(pipe.depth(np.array([0.01, 0.0, 0.25]))) == pytest.approx(-0.05)
    assert float(pipe.distance(np.array([0.05, 0.0, 0.43]))) == pytest.approx(0.03)
    assert np.allclose(pipe.extended(0.1).axis[0], [0.0, 0.0, 0.2])


def test_a_station_puts_the_tip_on_the_axis_and_the_inserted_arm_within_the_room() -> None:
    """spatial-confined's pipe: the approach station 20 mm before the entrance on the axis's
    line, then the station 40 mm in: its tip on the axis, the inserted 40 mm and the 20 mm of
    LEAD behind them within the room (radius - width / 2 - clearance), which binds."""
    scenario = load_scenario(resolve_scenario("spatial-confined"))
    arm = SpatialArm()
    model = arm.model(scenario)
    r = scenario.robot
    pipe = confined.Pipe(np.asarray(r.pipe, dtype=float), r.pipe_radius)
    room = r.pipe_radius - 0.5 * r.width - scenario.task.clearance
    axis = pipe.axis[1] - pipe.axis[0]
    before = pipe.axis[0] - 0.02 * axis / np.linalg.norm(axis)
    q, miss = confined.station(model, pipe, -0.02, room, arm.start_bends(scenario), 2e-3)
    assert miss < 1e-9 and np.allclose(kinematics.tip(model, q), before, atol=1e-9)
    q, miss = confined.station(model, pipe, 0.04, room, q, 2e-3)
    assert miss < 1e-9
    where = confined.arm_stations(model)
    inserted = where.arc_length >= where.arc_length[-1] - (0.04 + confined.LEAD) + 1e-9
    p = kinematics.points(model, q, where)[0][inserted]
    distance = pipe.extended(0.1).distance(p)
    assert np.all(distance <= room + 1e-6)
    assert distance.max() == pytest.approx(room, abs=1e-6)  # the constraint is what holds it


# ------------------------------------------------------------------ the camera frames


def test_the_3d_marker_frames_carry_their_ids_index_and_coordinates() -> None:
    """Two pictures of three markers: each CameraMarker3D names its marker and picture and
    carries its x, y, z, through the DBC (to its 0.1 mm resolution)."""
    from hil.devices import CameraNode, SyncContext
    from hil.vision import Camera, CameraEffects

    points = np.array([[0.0, 0.0, 0.0], [0.1, 0.2, -0.5], [0.05, -0.15, 0.3]])
    camera = Camera(CameraEffects(), np.random.default_rng(0), 0.02, 0.001)
    node = CameraNode(["a"], lambda v: points, 0, camera, dims=3)
    node.step(0.0, 0.001)
    node.step(0.02, 0.001)
    frames = [f for _, f in node.act(SyncContext(20, 20, 0.02), {})]
    protocol = Protocol()
    markers = [protocol.decode(protocol.encode(f)) for f in frames if isinstance(f, CameraMarker3D)]
    got = [(m.marker_id, m.frame_index, m.x, m.y, m.z) for m in markers]
    want = [(m, j, *points[m]) for j in (0, 1) for m in range(3)]
    assert [g[:2] for g in got] == [w[:2] for w in want]
    assert np.allclose([g[2:] for g in got], [w[2:] for w in want], atol=1e-4)
    headers = [f for f in frames if isinstance(f, CameraFrame)]
    assert [(h.frame_index, h.marker_mask, h.markers) for h in headers] == [
        (0, 0b111, 3),
        (1, 0b111, 3),
    ]


def test_a_planar_camera_ignores_3d_markers() -> None:
    camera = CameraAssembler(2)
    camera.add(CameraFrame(3, 0.0, 0b11, 2))
    camera.add(CameraMarker(0, 0.1, 0.2, 3, 0.0))
    camera.add(CameraMarker3D(1, 3, 0.1, 0.2, 0.3))
    assert not camera.complete(3)
    camera.add(CameraMarker(1, 0.3, 0.4, 3, 0.0))
    assert camera.complete(3)
    assert camera.take(3, 0.0).points.tolist() == [[0.1, 0.2], [0.3, 0.4]]


# ------------------------------------------------------------------ scenario checks, CLI


@pytest.mark.parametrize(
    ("name", "line", "message"),
    [
        (
            "spatial-point",
            "bends = [[1.0, 0, 0, 0, 0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0, 0, 0, 0, 0]]",
            "robot.bends[1]: step times must increase",
        ),
        ("spatial-shape", "curve = [[0.0, 0.0, 0.3]]", "robot.curve: a curve needs at least 2"),
    ],
)
def test_bad_steps_and_curves_get_one_line(
    tmp_path: Path, name: str, line: str, message: str
) -> None:
    path = scenario_file(tmp_path, name, {"pose": f'pose = "horizontal"\n{line}'})
    if "bends" in line:
        path.write_text(path.read_text().replace('kind = "point"', 'kind = "configuration"'))
    with pytest.raises(ScenarioError, match=re.escape(message)):
        load_scenario(path)


def test_hil_envelope_wants_50_samples(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "env"
    assert main(["envelope", "spatial-point", "--samples", "49", "--out", str(out)]) == 1
    assert "--samples: at least 50, got 49" in capsys.readouterr().err
    assert not out.exists()  # refused before anything is made


def test_drawn_goals_hold_their_pistons_in_the_middle_of_the_strokes(model: ArmModel) -> None:
    """The draws' pistons lie within the middle DRAW_SHARE (80 %) of every stroke, and span most
    of it."""
    scenario = load_scenario(resolve_scenario("spatial-point"))
    qs = task.draw_equilibria(SpatialArm(), scenario, 6, 1)
    pistons = statics.pistons_for(model, qs).x
    share = (pistons / model.stroke - 0.5) / task.DRAW_SHARE
    assert np.all(np.abs(share) <= 0.5 + 1e-6)
    assert share.min() < -0.4 and share.max() > 0.4
