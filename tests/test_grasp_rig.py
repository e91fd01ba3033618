"""The gripper and the grasp task in the rig (issue 12): a short planar-grasp run opens the fingers
and approaches the object without touching it, the camera reports the object's marker after the
arm's, the task's object comes from the seed, and bad gripper or grasp keys are one-line errors.
The object tracker localises a static object and gates outliers; the KF re-acquires a segment
whose model has lost it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controllers.estimation import CameraNoise
from controllers.object_tracking import ObjectTracker
from hil.errors import ScenarioError
from hil.run import RunOptions, run_scenario
from hil.scenario import load_scenario, resolve_scenario
from hil.summary import read_signals

GRASP = resolve_scenario("planar-grasp").read_text()


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def approach_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, dict, Path]:
    tmp = tmp_path_factory.mktemp("grasp")
    text = GRASP.replace("duration = 30.0", "duration = 2.5")
    scenario = load_scenario(write(tmp, text))
    summary = run_scenario(scenario, RunOptions(out=tmp / "run", inprocess=True, progress=False))
    return summary.summary, read_signals(tmp / "run" / "signals.csv"), tmp / "run"


def test_the_fingers_open_and_the_approach_does_not_touch_the_object(approach_run) -> None:
    summary, signals, _ = approach_run
    from hil.scenario import load_scenario as load
    from robots.planar_arm.plant.rig import ROBOT

    pick, _ = ROBOT.grasp_layout(load(write_tmp(GRASP)))
    assert summary["pick"] == pytest.approx(list(pick))
    theta = np.asarray(signals["gripper_theta"])
    assert theta[-1] < -0.3  # opened towards theta_open = -0.4
    phase = np.asarray(signals["phase"])
    assert phase[np.isfinite(phase)][-1] in (1, 2)  # on its way (moving or settling)
    xy = np.column_stack([signals["object1_x"], signals["object1_y"]])
    assert np.max(np.linalg.norm(xy - np.array(pick), axis=1)) < 1e-3  # untouched
    assert summary["approach_disturbance"] < 1e-3
    assert np.all(np.asarray(signals["object1_upright"]) == 1.0)
    forces = np.asarray(signals["finger_force_left"]) + np.asarray(signals["finger_force_right"])
    assert np.all(forces == 0.0)


def test_a_grasp_run_is_byte_identical_with_the_controller_in_its_own_process(
    approach_run, tmp_path: Path
) -> None:
    """Same seed, same results in both process modes (issue 12's acceptance): the gripper,
    the object, its marker and the Environment FMU's contact change nothing of that."""
    _, _, folder = approach_run
    text = GRASP.replace("duration = 30.0", "duration = 2.5")
    summary = run_scenario(
        load_scenario(write(tmp_path, text)), RunOptions(out=tmp_path / "run", progress=False)
    ).summary
    assert summary["controller_process"] == "process"
    for name in ("can.log", "signals.csv"):
        assert (tmp_path / "run" / name).read_bytes() == (folder / name).read_bytes(), name


def write_tmp(text: str) -> Path:
    import tempfile

    folder = Path(tempfile.mkdtemp())
    return write(folder, text)


def test_the_camera_reports_the_object_marker_after_the_arms(approach_run) -> None:
    from rigbus.protocol import Protocol

    _, signals, folder = approach_run
    protocol = Protocol()
    seen = set()
    for line in (folder / "can.log").read_text().splitlines():
        frame_id = int(line.split()[2].split("#")[0], 16)
        if frame_id == protocol.database.get_message_by_name("CameraMarker7").frame_id:
            seen.add(frame_id)
    assert seen  # marker 7 = the object, after the base and six segment ends


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            "[robot.gripper]\n",
            "[robot.gripper]\nfinger_colour = 2\n",
            r"robot\.gripper\.finger_colour: unknown key",
        ),
        ("[robot.gripper]\n", "[robot.gripper]\ntheta_open = 2.0\n", r"robot\.gripper\.theta_open"),
        (
            "[robot.gripper]\ntheta_closed",
            "[robot.segment]\ntheta_start",
            r"robot\.gripper: must be given when task\.kind is 'grasp'",
        ),
        ("grasp_time = 1.0", "grasp_time = -1.0", r"task\.grasp_time: must be positive"),
        ("torque_std = 0.01", "torque_std = 0.0", r"controller\.torque_std: must be positive"),
        (
            "objects = [{ radius = 0.0125, mass = 0.005, height = 0.05 }]",
            "objects = [{ x = 0.1, y = 0.1 }]",
            r"objects\[0\]\.x: placed by the task",
        ),
        (
            "objects = [{ radius = 0.0125, mass = 0.005, height = 0.05 }]",
            "objects = []",
            r"robot\.environment\.objects: must be given when task\.kind is 'grasp'",
        ),
        (
            "objects = [{ radius = 0.0125, mass = 0.005, height = 0.05 }]",
            "objects = 5",
            r"robot\.environment\.objects: must be a list of at most 4 tables, got 5",
        ),
        (
            "objects = [{ radius = 0.0125, mass = 0.005, height = 0.05 }]",
            "objects = [{ radius = -1, mass = 0.005, height = 0.05 }]",
            r"robot\.environment\.objects\[0\]\.radius: -1 is outside the allowed range",
        ),
        (
            "objects = [{ radius = 0.0125, mass = 0.005, height = 0.05 }]",
            "objects = [{ radius = 0.0125, mass = 0.005, height = 0.05 }, 3]",
            r"robot\.environment\.objects\[1\]: a table",
        ),
        (
            "objects = [{ radius = 0.0125, mass = 0.005, height = 0.05 }]",
            "objects = [{ radius = 0.3, mass = 0.005, height = 0.05 }]",
            r"task: grasp task: no object and place found in 200 draws for an object of radius",
        ),
    ],
)
def test_gripper_and_grasp_keys_are_checked(
    tmp_path: Path, old: str, new: str, message: str
) -> None:
    assert old in GRASP
    with pytest.raises(ScenarioError, match=message) as caught:
        load_scenario(write(tmp_path, GRASP.replace(old, new, 1)))
    assert "\n" not in str(caught.value)


def test_a_gripper_needs_the_environment(tmp_path: Path) -> None:
    start = GRASP.index("[robot.environment]")
    text = GRASP[:start] + GRASP[GRASP.index("[camera]") :]
    with pytest.raises(
        ScenarioError, match=r"robot\.environment: must be given when robot\.gripper is given"
    ):
        load_scenario(write(tmp_path, text))


def test_the_object_comes_from_the_seed(tmp_path: Path) -> None:
    from robots.planar_arm.plant.rig import ROBOT

    one = ROBOT.grasp_layout(load_scenario(write(tmp_path, GRASP)))
    again = ROBOT.grasp_layout(load_scenario(write(tmp_path, GRASP)))
    other = ROBOT.grasp_layout(
        load_scenario(write(tmp_path, GRASP.replace("seed = 1", "seed = 2")))
    )
    assert one == again and one != other


def test_the_object_tracker_averages_noise_and_gates_outliers() -> None:
    rng = np.random.default_rng(3)
    camera = CameraNoise(noise=5e-4)
    tracker = ObjectTracker(1, camera)
    truth = np.array([0.2, 0.1])
    gated = 0
    for k in range(100):
        z = truth + rng.normal(0.0, 5e-4, 2)
        if k == 50:
            z = truth + np.array([0.02, 0.0])  # an outlier 20 mm off
        gated += tracker.update(z[np.newaxis, :], 0.01 * k)
    assert gated == 1
    # better than one picture (its error is 0.63 mm on average at 0.5 mm per axis)
    assert np.linalg.norm(tracker.x[0] - truth) < 3.5e-4
    unseen = ObjectTracker(1, camera)
    unseen.update(np.full((1, 2), np.nan), 0.0)
    assert np.isnan(unseen.x).all()


def test_the_kf_reacquires_a_segment_its_model_has_lost() -> None:
    from controllers import kinematics
    from controllers.bend_filter import REACQUIRE
    from controllers.estimation import BendModel, MarkerFrame
    from controllers.segment_kf import SegmentKalmanEstimator

    bend = BendModel(length=0.06, inertia=5.4e-6, k_bend=0.025, d_bend=6e-3, G_a=7.7e-7)
    estimator = SegmentKalmanEstimator([bend], (0.0, 0.0, 0.0), CameraNoise(noise=5e-4), 0.01)
    # the camera sees the segment bent by 10 1/m, the model (no pressure) expects it straight
    points = kinematics.markers([10.0], [0.06], (0.0, 0.0, 0.0))[:, :2]
    kappas = []
    for k in range(1, 60):
        estimate = estimator.update(0.01 * k, {}, [MarkerFrame(0.01 * k, points)])
        kappas.append(estimate.kappa[0])
    # the model pulls it back between pictures, the camera's word is taken again every
    # REACQUIRE pictures at most: the estimate stays near the truth instead of near zero
    assert min(kappas[20:]) > 7.0 and max(kappas[20:]) < 11.0
    assert REACQUIRE > 1  # a single outlier is still gated


@pytest.mark.parametrize(
    ("end", "upright", "finger", "success"),
    [
        ((0.1085, 0.2), 1.0, 0.0, True),  # 8.5 mm off, standing, released
        ((0.1115, 0.2), 1.0, 0.0, False),  # 11.5 mm off
        ((0.1, 0.2), 0.0, 0.0, False),  # toppled
        ((0.1, 0.2), 1.0, 0.05, False),  # a finger still on it
    ],
)
def test_grasp_success_is_place_upright_released(end, upright, finger, success) -> None:
    from types import SimpleNamespace

    from robots.planar_arm.controller.tasks import PHASE
    from robots.planar_arm.plant.tasks import _grasp

    pick, place = (0.2, 0.1), (0.1, 0.2)
    t = np.arange(0.0, 3.0, 0.01)
    phase = np.select(
        [t < 1.0, t < 1.5, t < 2.5],
        [PHASE["moving"], PHASE["grasping"], PHASE["moving"]],
        PHASE["done"],
    ).astype(float)
    carry = np.clip((t - 1.5) / 1.0, 0.0, 1.0)[:, None]
    xy = np.array(pick) + carry * (np.array(end) - np.array(pick))
    held = ((t >= 1.2) & (t < 2.6)).astype(float) * 0.3
    signals = {
        "object1_x": xy[:, 0],
        "object1_y": xy[:, 1],
        "object1_upright": np.where(t < 2.8, 1.0, upright),
        "finger_force_left": np.where(t < 2.9, held, finger),
        "finger_force_right": held,
    }
    robot = SimpleNamespace(grasp_layout=lambda scenario: (pick, place))
    metrics = _grasp(robot, None, t, signals, phase)
    assert metrics["success"] is success
    assert metrics["place_error"] == pytest.approx(np.hypot(end[0] - 0.1, end[1] - 0.2))
    assert metrics["grasped"] is True and metrics["approach_disturbance"] == 0.0
    assert metrics["time_to_place"] == pytest.approx(2.5)
