"""The planar arm's soft gripper (issue 12): `[robot.gripper]` to a FeaSegment FMU (the finger
pair), its own DriveCylinder FMU and drive node (the seventh DOF), wired into the Environment
FMU's contact.

    [robot.gripper]
    finger_length = 0.04          # geometry
    (robots.planar_arm.controller.gripper.GripperGeometry), [m] and [rad]
    theta_closed = 1.2
    [robot.gripper.segment]       # the finger pair's FeaSegment parameters over GRIPPER_SEGMENT
    k_bend = 0.01
    [robot.gripper.cylinder]      # its drive cylinder's over the DriveCylinder defaults
    stroke = 0.05

The fingers' channels are fed in parallel by one cylinder, so the pair is one FeaSegment whose
stiffness, damping, mass and dV/dtheta are the two fingers' sums and whose length is a finger's.
The gripper's drive is node `segments + 1` (DriveStatus/DriveCommand of that index); its FMUs are
`cylinder{node}` and `gripper`. It needs `[robot.environment]`: the fingers act on the world only
through its contact. Invariant: the FeaSegment's bend angle is the Environment's gripper_theta.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from hil.schema import Key, Range, Ref, Table, not_negative, positive
from robots.planar_arm.controller.gripper import GripperGeometry

if TYPE_CHECKING:
    from hil.scenario import Scenario

SEGMENT_FMU, CYLINDER_FMU = "FeaSegment", "DriveCylinder"
# [estimate] The finger pair as one actuator (sums of two fingers of 4 g, 40 mm): free, the pair
# curls to 1 rad at 36 mm of piston travel and to its 1.4 rad limit at full stroke; blocked on
# an object at 0.6 rad with the piston at the 1.35 rad setting it squeezes with ~0.016 N m,
# about 0.25 N per finger (a held 5 g object drags 0.015 N of table friction).
GRIPPER_SEGMENT: dict[str, float] = {
    "length": 0.04,
    "mass": 0.008,
    "k_bend": 0.02,
    "d_bend": 4e-3,
    "G_a": 5e-7,
    "V_ch0": 3e-6,
    "C_a": 5e-11,
    "theta_max": 1.4,
}
OWN_TABLES = ("segment", "cylinder")
_GEOMETRY = GripperGeometry()  # its defaults
TABLE = Table(
    "robot.gripper",
    (
        Key("finger_length", float, _GEOMETRY.finger_length, "m", "a finger's length", positive()),
        Key(
            "finger_width",
            float,
            _GEOMETRY.finger_width,
            "m",
            "a finger's width (its capsule's diameter)",
            not_negative(),
        ),
        Key(
            "root_offset",
            float,
            _GEOMETRY.root_offset,
            "m",
            "each finger's root, sideways from the tip",
            not_negative(),
        ),
        Key(
            "grasp_offset",
            float,
            _GEOMETRY.grasp_offset,
            "m",
            "where a held object's centre sits, ahead of the tip",
            positive(),
        ),
        Key(
            "theta_open",
            float,
            _GEOMETRY.theta_open,
            "rad",
            "the open fingers' bend (approach, release)",
            Range(hi=Ref("robot.gripper.theta_closed"), hi_open=True),
        ),
        Key(
            "theta_closed",
            float,
            _GEOMETRY.theta_closed,
            "rad",
            "the bend the closing stroke aims for (beyond contact)",
        ),
    ),
    skip=OWN_TABLES,
    doc="the finger pair at the tip (robots.planar_arm.controller.gripper.GripperGeometry); needs "
    "[robot.environment]",
)


def present(scenario: Scenario) -> bool:
    return getattr(scenario.robot, "gripper", None) is not None


def node(scenario: Scenario) -> int:
    """The gripper drive's node number."""
    return int(scenario.robot.segments) + 1


def geometry(scenario: Scenario) -> GripperGeometry:
    """The fingers' geometry from `[robot.gripper]` (TABLE, checked with the scenario)."""
    raw: Mapping[str, Any] = scenario.robot.gripper or {}
    return GripperGeometry(**{k: float(v) for k, v in raw.items() if k not in OWN_TABLES})


def table(scenario: Scenario, name: str) -> dict[str, float]:
    """What `[robot.gripper.<name>]` sets (name: segment or cylinder), checked as numbers."""
    from hil.scenario import fail

    raw = (scenario.robot.gripper or {}).get(name, {})
    if not isinstance(raw, Mapping):
        raise fail(scenario.source, f"robot.gripper.{name}", "must be a table of parameters")
    return {k: _number(scenario.source, f"robot.gripper.{name}.{k}", v) for k, v in raw.items()}


def segment_values(scenario: Scenario) -> dict[str, float]:
    """The finger pair's FeaSegment parameters given (GRIPPER_SEGMENT, the scenario's, and the
    length of a finger)."""
    values = {**GRIPPER_SEGMENT, **table(scenario, "segment")}
    values["length"] = geometry(scenario).finger_length
    return values


def environment_parameters(scenario: Scenario) -> dict[str, float]:
    """The Environment FMU's gripper parameters."""
    g = geometry(scenario)
    segment = segment_values(scenario)
    return {
        "gripper": 1.0,
        "finger_length": g.finger_length,
        "finger_width": g.finger_width,
        "finger_root_offset": g.root_offset,
        "finger_mass": 0.5 * segment["mass"],
    }


def drive_connections(n: int, ports: Mapping[str, str]) -> list[tuple[str, str]]:
    """(source, target) wiring of drive node `n`: its device, its DriveCylinder `cylinder{n}`
    and the gas circuit the cylinder drives, whose `ports` (x_piston, p_a, p_b: full names) are
    a FeaSegment's (a segment, or the finger pair) or a segment's on the arm body."""
    return [
        (f"cylinder{n}.x", ports["x_piston"]),
        (ports["p_a"], f"cylinder{n}.p_a"),
        (ports["p_b"], f"cylinder{n}.p_b"),
        (f"drive{n}.x_ref", f"cylinder{n}.x_ref"),
        (f"drive{n}.enable", f"cylinder{n}.enable"),
        (f"cylinder{n}.x", f"drive{n}.x"),
        (ports["p_a"], f"drive{n}.p_a"),
        (ports["p_b"], f"drive{n}.p_b"),
        (f"cylinder{n}.fault", f"drive{n}.servo_fault"),
    ]


def connections(scenario: Scenario) -> list[tuple[str, str]]:
    """The gripper's drive, cylinder and finger pair, and the fingers in the world's contact."""
    return [
        *drive_connections(
            node(scenario), {name: f"gripper.{name}" for name in ("x_piston", "p_a", "p_b")}
        ),
        ("gripper.theta", "environment.gripper_theta"),
        ("gripper.theta_dot", "environment.gripper_theta_dot"),
        ("environment.gripper_tau_ext", "gripper.tau_ext"),
    ]


def _number(file: str, key: str, value: Any) -> float:
    from hil.scenario import fail

    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise fail(file, key, f"must be a finite number, got {value!r}")
    return float(value)
