"""The gripper in the Environment FMU (issue 12): its fingers are where
robots/planar_arm/controller/gripper.py puts
them, their torques are the virtual work of their contact (on the fingers' bend angle and on every
segment of the arm that carries them), closed fingers hold an object through contact alone while
the arm swings it back and forth (open fingers leave it behind), and the tipping monitor flags a
knocked object but not one pushed slowly."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import pytest

from controllers import kinematics
from hil.fmu.build import BuiltFmu, build_fmu
from hil.fmu.slave import FmuSlave
from robots.planar_arm.controller.gripper import GripperGeometry, finger_points, grasp_point

LENGTH = 0.06
H = 1e-3
GEOMETRY = GripperGeometry()


@pytest.fixture(scope="module")
def environment_fmu() -> BuiltFmu:
    return build_fmu("Environment")


def gripper_params(segments: int, **extra: float) -> dict[str, float]:
    return {
        "n_segments": segments,
        "gripper": 1,
        "finger_length": GEOMETRY.finger_length,
        "finger_width": GEOMETRY.finger_width,
        "finger_root_offset": GEOMETRY.root_offset,
        "arm_mobility": 0.0,
        "coupling_delay": 0,
        **extra,
    }


def at_rest(
    fmu: BuiltFmu, params: Mapping[str, float], kappas: Sequence[float], theta: float
) -> dict[str, object]:
    inputs = {f"kappa_{i + 1}": k for i, k in enumerate(kappas)}
    with FmuSlave(fmu, "env", {**params, **inputs, "gripper_theta": theta}) as env:
        return {
            "tau": np.array([env.get(f"tau_ext_{i + 1}") for i in range(len(kappas))]),
            "tau_gripper": env.get("gripper_tau_ext"),
            "penetration": env.get("gripper_penetration"),
            "left": env.get("finger_force_left"),
            "right": env.get("finger_force_right"),
            "E_contact": env.get("E_contact"),
        }


def test_finger_penetration_follows_controllers_gripper(environment_fmu) -> None:
    kappas, theta = [4.0, -6.0], 0.6
    tip = tuple(kinematics.forward(kappas, [LENGTH] * 2, (0.0, 0.0, 0.0))[-1])
    left, right = finger_points(GEOMETRY, tip, theta)
    centre, radius = left[5] + np.array([0.006, -0.004]), 0.003  # beside the left finger only
    params = gripper_params(
        2, n_objects=1, object_x0_1=centre[0], object_y0_1=centre[1], object_radius_1=radius
    )
    out = at_rest(environment_fmu, params, kappas, theta)
    reach = radius + GEOMETRY.finger_width / 2
    expected = max(reach - np.linalg.norm(p - centre) for p in left[1:])
    assert expected > 5e-4  # the object really touches the finger
    assert out["penetration"] == pytest.approx(expected, abs=1e-12)
    assert out["left"] > 0.0 and out["right"] == 0.0


def test_finger_torques_are_the_virtual_work_of_their_contact(environment_fmu) -> None:
    # a disk pinched between the fingers, off-centre: tau = -dE/dq for the fingers' bend and
    # for each segment carrying them
    kappas, theta = np.array([3.0, -4.0]), 0.7
    tip = tuple(kinematics.forward(kappas, [LENGTH] * 2, (0.0, 0.0, 0.0))[-1])
    centre = grasp_point(GEOMETRY, tip) + np.array([0.002, 0.003])
    params = gripper_params(
        2,
        d_contact=0.0,
        n_objects=1,
        object_x0_1=centre[0],
        object_y0_1=centre[1],
        object_radius_1=0.015,
    )
    out = at_rest(environment_fmu, params, kappas, theta)
    assert out["left"] > 0.05 and out["right"] > 0.05  # both fingers touch it
    delta = 1e-7
    up = at_rest(environment_fmu, params, kappas, theta + delta)["E_contact"]
    down = at_rest(environment_fmu, params, kappas, theta - delta)["E_contact"]
    assert out["tau_gripper"] == pytest.approx(-(up - down) / (2 * delta), rel=1e-5)
    assert out["tau_gripper"] < 0.0  # the object resists closing
    for i in range(2):
        shift = np.zeros(2)
        shift[i] = delta / LENGTH
        up = at_rest(environment_fmu, params, kappas + shift, theta)["E_contact"]
        down = at_rest(environment_fmu, params, kappas - shift, theta)["E_contact"]
        assert out["tau"][i] == pytest.approx(-(up - down) / (2 * delta), rel=1e-5, abs=1e-9)


def swing(fmu: BuiltFmu, theta: float) -> tuple[float, float, float]:
    """A one-segment arm holding a disk at its grasp point swings 0.4 rad out and back (its
    motion prescribed); returns how far the disk travelled from its start at the far end, its
    distance from the grasp point at the end, and how far it moved in the hand (the tip's frame)
    between the far end and the end."""
    tip0 = tuple(kinematics.forward([0.0], [LENGTH], (0.0, 0.0, 0.0))[-1])
    centre = grasp_point(GEOMETRY, tip0)
    params = gripper_params(
        1,
        n_objects=1,
        object_x0_1=centre[0],
        object_y0_1=centre[1],
        object_radius_1=0.015,
        object_mass_1=0.01,
    )
    rate, period = 1.0, 0.8  # rad/s; out for half the period, back for the other half
    farthest = 0.0
    in_hand = []
    with FmuSlave(fmu, "env", {**params, "gripper_theta": theta}) as env:
        for k in range(round(period / H)):
            t = k * H
            sign = 1.0 if t < period / 2 else -1.0
            bend = rate * (t if sign > 0 else period - t)
            env.set("kappa_1", bend / LENGTH)
            env.set("theta_dot_1", sign * rate)
            env.do_step(t, H)
            at = np.array([env.get("object_x_1"), env.get("object_y_1")])
            farthest = max(farthest, float(np.linalg.norm(at - centre)))
            x, y, heading = kinematics.forward([bend / LENGTH], [LENGTH], (0.0, 0.0, 0.0))[-1]
            c, s = math.cos(heading), math.sin(heading)
            offset = at - np.array([x, y])
            in_hand.append((c * offset[0] + s * offset[1], -s * offset[0] + c * offset[1]))
        end = np.linalg.norm(at - grasp_point(GEOMETRY, tip0))
    drift = float(np.linalg.norm(np.subtract(in_hand[-1], in_hand[len(in_hand) // 2])))
    return farthest, float(end), drift


def test_closed_fingers_hold_an_object_through_contact_and_open_ones_do_not(
    environment_fmu,
) -> None:
    carried, held_end, drift = swing(environment_fmu, GEOMETRY.theta_closed)
    assert carried > 0.015  # it went out with the arm (the grasp point moves ~30 mm)
    # and came back with it, keeping its place in the hand: both fingers enclose it. The closed
    # fingers overlap the 15 mm disk by 14 mm at the grasp point, so the contact squeezes it
    # 14.5 mm back into the pocket at the fingers' roots (as resolved substeps of 1 us do too)
    assert drift < 2e-3 and held_end < 0.02
    pushed, left_end, _ = swing(environment_fmu, GEOMETRY.theta_open)
    assert left_end > 5e-3  # open fingers pushed it out and left it there


def knock(fmu: BuiltFmu, rate: float) -> tuple[float, float, float]:
    """A straight segment sweeps into a disk beside its tip at `rate` [rad/s]; the disk stands
    40 mm tall, radius 10 mm, and the arm touches it 30 mm up. Returns (upright, largest tilt,
    distance moved)."""
    params = {
        "n_segments": 1,
        "arm_mobility": 0.0,
        "coupling_delay": 0,
        "contact_height": 0.03,
        "n_objects": 1,
        "object_x0_1": 0.05,
        "object_y0_1": 0.021,
        "object_radius_1": 0.01,
        "object_height_1": 0.04,
        "object_mass_1": 0.01,
    }
    sweep = 0.4  # rad
    tilt = 0.0
    with FmuSlave(fmu, "env", params) as env:
        steps = round((sweep / rate + 0.2) / H)
        for k in range(steps):
            t = k * H
            moving = t * rate < sweep
            env.set("kappa_1", min(rate * t, sweep) / LENGTH)
            env.set("theta_dot_1", rate if moving else 0.0)
            env.do_step(t, H)
            tilt = max(tilt, env.get("object_tilt_1"))
        moved = math.hypot(env.get("object_x_1") - 0.05, env.get("object_y_1") - 0.021)
        return env.get("object_upright_1"), tilt, moved


def test_a_knocked_object_tips_over_and_a_slowly_pushed_one_stands(environment_fmu) -> None:
    upright, tilt, moved = knock(environment_fmu, 0.3)
    assert upright == 1.0 and moved > 5e-3  # pushed along, standing
    assert tilt < 0.05
    upright, tilt, moved = knock(environment_fmu, 30.0)
    # it falls the moment its centre of mass passes the edge: the tilt is frozen there
    assert upright == 0.0 and math.atan2(0.02, 0.04) <= tilt < math.atan2(0.02, 0.04) + 0.1
