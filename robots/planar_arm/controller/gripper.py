"""The soft gripper at the planar arm's tip (issue 12): geometry and finger kinematics.

A pair of fluidic elastomer fingers, both fed by one drive cylinder (the arm's seventh DOF): the
two channels are in parallel, so both fingers bend by the same angle `theta` [rad], mirrored.
Positive `theta` closes (each finger curls towards the gripper's axis), negative opens. Finger
roots sit `root_offset` to either side of the axis at the arm's tip; each finger is a
constant-curvature arc of `finger_length` (kinematics as one PCC segment, controllers.kinematics)
and, for contact, a capsule of radius `finger_width / 2` around it.

Invariant: this module and fmus/Environment/model.c compute the same finger points (the plant's
contact and the controller's planning agree on where the fingers are; tested).

[estimate] The thesis's planar grasping arm has "a soft gripper" with two fingers but gives no
dimensions here; the values below are sized to its objects (disks of 25-30 mm diameter): 40 mm
fingers, 8 mm wide, roots 22 mm either side of the axis (a 36 mm clear gap between the straight
fingers), opening to about 50 mm at the fingertips at -0.4 rad and curling 18 mm inwards at
+1 rad. A grasped object sits `grasp_offset` ahead of the tip, between the fingers' middles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controllers.kinematics import segment_end

FINGER_SAMPLES = 8  # points per finger, as the Environment FMU samples the arm's segments


@dataclass(frozen=True)
class GripperGeometry:
    """The finger pair [m, rad]; see the module docstring."""

    finger_length: float = 0.04
    finger_width: float = 0.008
    root_offset: float = 0.022
    grasp_offset: float = 0.03  # where the object's centre sits when grasped, ahead of the tip
    theta_open: float = -0.4  # the bend angle of open fingers (approach, release)
    theta_closed: float = 1.0  # the bend angle the closing stroke aims for (beyond contact)

    def clear_width(self, theta: float) -> float:
        """Narrowest clear gap between the two finger capsules at bend angle `theta` [m] (the
        widest object that passes between them)."""
        a, b = finger_points(self, (0.0, 0.0, 0.0), theta, samples=64)
        return float(np.min(np.abs(a[:, 1] - b[:, 1]))) - self.finger_width


def finger_points(
    geometry: GripperGeometry,
    tip: tuple[float, float, float],
    theta: float,
    samples: int = FINGER_SAMPLES,
) -> tuple[np.ndarray, np.ndarray]:
    """Points along the left and right finger (each shape (samples + 1, 2), root first) [m] for
    the arm's tip pose `tip` (x, y, heading) and the fingers' bend angle `theta` [rad]."""
    x, y, heading = tip
    normal = (-math.sin(heading), math.cos(heading))  # the tip's left
    fingers = []
    for side in (1.0, -1.0):  # left finger curls right (towards the axis) when closing
        root = (
            x + side * geometry.root_offset * normal[0],
            y + side * geometry.root_offset * normal[1],
            heading,
        )
        kappa = -side * theta / geometry.finger_length
        points = [root[:2]]
        for k in range(1, samples + 1):
            end = segment_end(root, kappa, geometry.finger_length * k / samples)
            points.append((end[0], end[1]))
        fingers.append(np.array(points))
    return fingers[0], fingers[1]


def grasp_point(geometry: GripperGeometry, tip: tuple[float, float, float]) -> np.ndarray:
    """Where a grasped object's centre sits for the tip pose `tip` [m]."""
    x, y, heading = tip
    reach = geometry.grasp_offset
    return np.array([x + reach * math.cos(heading), y + reach * math.sin(heading)])


def tip_for_grasp(
    geometry: GripperGeometry, centre: tuple[float, float], heading: float, standoff: float = 0.0
) -> tuple[float, float, float]:
    """The tip pose that holds an object's centre `centre` at the grasp point, the gripper
    pointing along `heading`, backed off by `standoff` [m] along the axis."""
    reach = geometry.grasp_offset + standoff
    return (
        centre[0] - reach * math.cos(heading),
        centre[1] - reach * math.sin(heading),
        heading,
    )
