"""Grasp-and-place with the planar arm's soft gripper (issue 12): the controller's state machine
above the per-segment curvature controllers and the gripper's drive.

The controller is told where to place the object, never where it is: it finds the object by its
camera marker (controllers.object_tracking.ObjectTracker). Stages, each reported in TaskState
(index: 0 approach, 1 carry, 2 retreat; phase as named):
  1. idle: the pistons held while the estimators acquire the arm and the object;
  2. moving (approach): the fingers open and the arm follows the approach plan
     (robots.planar_arm.controller.grasp_planner.plan_approach: concentric circles around the
     estimated object that shrink onto it without touching it), waypoint after waypoint by
     realisable curvature moves;
  3. settling: the curvature loops settle on the grasp configuration (the estimated tip within
     `tolerance` of the plan's tip for `settle_time`, or `max_time` at most); if the camera
     sees the object where closing fingers would not take hold of it (CAPTURE_SLACK: the arm
     lags its plan, and a finger can knock the object), the approach is planned again to where
     it is now (backing straight off first if the arm is too close to plan from), at most
     MAX_REAPPROACHES times, and then the task ends;
  4. grasping: the fingers close for `grasp_time`; contact alone holds the object;
  5. moving (carry): the held object's centre goes to the place location (plan_carry), then
     settling on the camera's view of the object until it is on target and at rest (see
     GraspControl._place);
  6. releasing: the fingers open for `grasp_time`;
  7. moving (retreat): the gripper backs off along its axis out of the object's way
     (plan_retreat); then done, holding the last configuration.
A plan that cannot be made (the object or the place out of reach from where the arm is) ends the
task in `done` where the arm is (`note` says why) instead of stopping the controller.
Invariant: every curvature reference stays within the plan's bounds and its rate within each
drive's (CurvatureMove), and the gripper's setpoint only ramps between its three pistons.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from controllers import kinematics
from controllers.estimation import DriveReading, Estimate
from rigbus.protocol import ControllerState, DriveCommand, Protocol, TaskState
from robots.planar_arm.controller import grasp_planner
from robots.planar_arm.controller.curvature_control import CurvatureControl
from robots.planar_arm.controller.grasp_carry import plan_carry
from robots.planar_arm.controller.gripper import grasp_point
from robots.planar_arm.controller.ik import solve_ik
from robots.planar_arm.controller.tasks import PHASE, CurvatureMove

if TYPE_CHECKING:
    from robots.planar_arm.controller.config import ControllerConfig

LEGS = ("approach", "carry", "retreat")
CORRECTION_LIMIT = 0.04  # [m] bound of the integrated task-space correction while settling (a held
# object sits up to a centimetre off the nominal grasp point, and the estimate carries a bias
# of a centimetre or two under its load)
# [m] the correction integrates only while the estimated tip is this close to the goal: further
# off, the arm is still on its way and integrating would wind the correction up (as
# robots.planar_arm.controller.task_space does)
WINDUP_LIMIT = 0.005
ARRIVAL_TIME = 1.0  # [s] settling this long, the arm has arrived however biased its estimate
# [m/rad] the settling IK weighs the gripper's heading lightly: the object is a disk, a few
# degrees of heading cost nothing, a few millimetres of position can make the fingers miss
HEADING_WEIGHT = 0.005
RETREAT_STEP = 0.005  # [m] between the warm-started poses of a straight retreat
# [s, m] a carried object is at rest when its estimated centre has stayed within REST_DRIFT of
# where it is now for REST_WINDOW on target (0.6 mm/s: the tracker's noise is ~0.1 mm)
REST_WINDOW = 0.5
REST_DRIFT = 3e-4
# [m] where closing fingers take hold of an object: its centre between the open fingers' inner
# faces (up to CAPTURE_SLACK of contact penetration: a finger that pushed it has it on its inner
# face), and at most CAPTURE_BACK behind or CAPTURE_AHEAD ahead of the grasp point along the
# gripper's axis (towards the palm, or the fingertips: an object whose centre is past them is
# pushed out; measured, fingers closing on objects pushed 5-7 mm ahead held them all). Settled
# on the grasp pose with the object seen elsewhere (a finger knocked it), the approach is
# planned again, at most MAX_REAPPROACHES times, and then the task ends there
CAPTURE_SLACK = 2e-3
CAPTURE_BACK = 1e-2
CAPTURE_AHEAD = 1e-2
MAX_REAPPROACHES = 3
# [m] the approach's clearance when none keeps grasp_planner.MARGIN from the arm's estimated start
APPROACH_MARGIN_FALLBACK = 5e-4
STROKE_SHARE = 0.5  # of grasp_time the fingers' closing or opening stroke is spread over


class GraspControl:
    """Grasp-and-place; see the module."""

    def __init__(self, config: ControllerConfig, protocol: Protocol) -> None:
        if config.plan is None or config.gripper is None:
            raise ValueError("plan: grasp-and-place needs a task plan and a gripper")
        self.config = config
        self.plan = config.plan
        self.gripper = config.gripper
        self.curvature = CurvatureControl(config, protocol)
        self.lengths = np.array(config.lengths)
        self.base = config.base
        self.lower = np.array(self.plan.kappa_min)
        self.upper = np.array(self.plan.kappa_max)
        self.rates = np.array(self.plan.kappa_rate)
        # a multibody arm's pistons per curvature acceleration: its moves' ramps are shaped to it
        # a multibody arm's moves ramp over a period of its closed loop's poles (the inertial
        # loop follows them; ramped faster, the drives swing against their stroke's ends)
        arm = config.arm_gains
        self.accel_time = self.plan.accel_time
        if arm is not None:
            self.accel_time = max(self.accel_time, 2.0 * math.pi / arm.pole)
        self.reference = np.zeros(config.segments)
        self.leg = 0
        self.phase = PHASE["idle"]
        self.since = 0.0  # when the current phase (or waypoint) began [s]
        self.on_target_since: float | None = None
        self.waypoints: list[tuple[np.ndarray, tuple[float, float, float]]] = []
        self.waypoint = 0
        self.move: CurvatureMove | None = None
        self.setpoint = self.gripper.x_start  # the gripper drive's piston setpoint [m]
        self.stroke_from = self.gripper.x_start  # where its current stroke began [m]
        self.stroke_start = 0.0  # when [s]
        self.heading = 0.0  # the gripper's approach heading [rad]
        self.target = np.array(self.plan.targets[0], float)  # where the object is to go
        self.found: np.ndarray | None = None  # the object's estimated centre when planned
        self.correction = np.zeros(2)  # integrated task-space correction of the goal [m]
        self.seen = self.target.copy()  # the object's latest estimated centre [m]
        self.solution = np.zeros(config.segments)  # the last IK solution (warm start)
        self.nominal = np.zeros(config.segments)  # the approach plan's grasp configuration
        self.reapproaches = 0  # approaches planned again because the object had moved
        self.note = ""  # why the last plan failed (the task ends there if nothing else works)
        # the carried object's recent estimates (time, centre): has it come to rest?
        self.track: deque[tuple[float, np.ndarray]] = deque()

    # ------------------------------------------------------------------ the cycle

    def compute(
        self, cycle: int, t: float, estimate: Estimate, drives: Mapping[int, DriveReading]
    ) -> list[Any]:
        kappa = np.asarray(estimate.kappa, float)
        if estimate.objects is not None and not np.isnan(estimate.objects[0]).any():
            self.seen = np.array(estimate.objects[0], float)
        if self.phase == PHASE["idle"]:
            objects = estimate.objects
            seen = objects is not None and not np.isnan(objects[0]).any()
            if t >= self.plan.acquire_time - 1e-9 and seen:
                assert objects is not None
                if not self._approach(t, kappa, objects[0]):
                    self.reference = np.clip(kappa, self.lower, self.upper)
                    self._enter(t, PHASE["done"])  # no approach: stay where the arm is
            else:
                return self._hold(cycle, estimate, drives)
        self._advance(t, kappa)
        moving = self.phase == PHASE["moving"] and self.move is not None
        motion = self.move.motion(t - self.since) if moving and self.move else None
        frames = self.curvature.command(cycle, self.reference, estimate, drives, motion)
        frames.append(DriveCommand(self.gripper.node, self._gripper_piston(t), True, cycle))
        point = self._reference_point()
        frames.append(
            TaskState(self.leg, self.phase, float(point[0]), float(point[1]), cycle % 256)
        )
        return frames

    def _hold(
        self, cycle: int, estimate: Estimate, drives: Mapping[int, DriveReading]
    ) -> list[Any]:
        """Every piston held where it is (the estimators are still acquiring)."""
        frames: list[Any] = []
        lo, hi = self.curvature.shown_range
        for i in range(self.config.segments):
            reading = drives.get(i + 1)
            piston = reading.piston_position if reading is not None else self.config.x_mid[i]
            kappa = min(max(float(estimate.kappa[i]), lo), hi)
            frames.append(DriveCommand(i + 1, piston, True, cycle))
            frames.append(ControllerState(i + 1, kappa, kappa, cycle))
        frames.append(DriveCommand(self.gripper.node, self.setpoint, True, cycle))
        frames.append(
            TaskState(0, PHASE["idle"], float(self.target[0]), float(self.target[1]), cycle % 256)
        )
        return frames

    def _gripper_piston(self, t: float) -> float:
        """The gripper's piston setpoint now: its strokes are ramps over STROKE_SHARE of
        grasp_time (trapezoidal), so closing fingers centre an object they reach off-centre
        instead of knocking it away."""
        from robots.planar_arm.controller.tasks import trapezoid_fraction

        duration = STROKE_SHARE * self.plan.grasp_time
        share = trapezoid_fraction(t - self.stroke_start, duration, 0.25 * duration)
        return self.stroke_from + (self.setpoint - self.stroke_from) * share

    def _stroke(self, t: float, to: float) -> None:
        self.stroke_from = self._gripper_piston(t)
        self.stroke_start = t
        self.setpoint = to

    def _reference_point(self) -> np.ndarray:
        """Where the plan holds the object's centre now: the grasp point of the current
        waypoint's tip pose (the estimated object before any plan)."""
        if not self.waypoints:
            return self.target if self.found is None else self.found
        _, pose = self.waypoints[min(self.waypoint, len(self.waypoints) - 1)]
        return grasp_point(self.gripper.geometry, pose)

    # ------------------------------------------------------------------ stages

    def _advance(self, t: float, kappa: np.ndarray) -> None:
        waited = t - self.since
        if self.phase == PHASE["moving"]:
            assert self.move is not None
            self.reference = self.move.value(waited)
            if waited >= self.move.duration:
                if self.waypoint + 1 < len(self.waypoints):
                    self.waypoint += 1
                    self._move_to(t, self.waypoints[self.waypoint][0])
                else:
                    self._enter(t, PHASE["settling"])
        elif self.phase == PHASE["settling"]:
            self._settle(t, kappa)
        elif self.phase == PHASE["grasping"] and waited >= self.plan.grasp_time:
            self.leg = 1
            carry = None
            # from where the arm holds the object, else from the approach plan's grasp
            # configuration (the settling moved the arm a little off it; the first carry move
            # takes it back)
            for start in (self.reference, self.nominal):
                try:
                    carry = self._plan_carry(start, self.heading)
                    break
                except ValueError as exc:
                    self.note = str(exc)
            if carry is None:
                self._enter(t, PHASE["done"])  # no way to the place: stay, holding the object
                return
            self.heading = carry.heading  # the heading the object is placed with
            self._follow(t, carry.waypoints)
        elif self.phase == PHASE["releasing"] and waited >= self.plan.grasp_time:
            self.leg = 2
            # back off from where the camera sees the released object, through the approach
            # circles, clear of it
            where = (float(self.seen[0]), float(self.seen[1]))
            try:
                retreat = grasp_planner.plan_retreat(
                    where,
                    self.plan.object_radius,
                    self.reference,
                    self.heading,
                    self.lengths,
                    self.base,
                    self.lower,
                    self.upper,
                    self.gripper.geometry,
                )
            except ValueError:
                retreat = None
            if retreat is not None:
                self._follow(t, retreat.waypoints)
                return
            # still touching it (pressed into the palm): straight back along the gripper's axis
            if not self._back_off(t):
                self._enter(t, PHASE["done"])  # no way back: stay, released

    def _back_off(self, t: float) -> bool:
        """Back the gripper straight off along its axis to the outer approach circle, in
        warm-started steps; False if not even the first step can be solved."""
        outer = grasp_planner.default_radii(self.plan.object_radius, self.gripper.geometry)[0]
        x, y, heading = kinematics.forward(self.reference, self.lengths, self.base)[-1]
        waypoints, previous = [], self.reference
        for standoff in np.arange(RETREAT_STEP, outer + 1e-9, RETREAT_STEP):
            back = float(standoff)
            pose = (x - back * np.cos(heading), y - back * np.sin(heading), float(heading))
            result = solve_ik(
                np.array(pose[:2]),
                previous,
                self.lengths,
                self.base,
                self.lower,
                self.upper,
                heading=pose[2],
            )
            if not result.converged:
                break
            waypoints.append((result.kappas, pose))
            previous = result.kappas
        if waypoints:
            self._follow(t, waypoints)
        return bool(waypoints)

    def _approach(self, t: float, kappa: np.ndarray, centre: np.ndarray) -> bool:
        """Plan the approach to the object seen at `centre` from the estimated curvatures
        `kappa` and start it; False (and `note` says why) if there is none."""
        start = np.clip(kappa, self.lower, self.upper)
        approach = None
        # an approach from whose grasp the object can be carried to the place; with a thinner
        # margin if the arm's estimated start leaves none (the task was drawn with more)
        for margin in (grasp_planner.MARGIN, APPROACH_MARGIN_FALLBACK):
            try:
                approach = grasp_planner.plan_approach(
                    (float(centre[0]), float(centre[1])),
                    self.plan.object_radius,
                    start,
                    self.lengths,
                    self.base,
                    self.lower,
                    self.upper,
                    self.gripper.geometry,
                    margin=margin,
                    accept=self._carriable,
                )
                break
            except ValueError as exc:
                self.note = str(exc)
        if approach is None:
            return False
        self.found = centre.copy()
        self.reference = start.copy()
        self.heading = approach.heading
        self.nominal = np.asarray(approach.waypoints[-1][0], float)
        self._stroke(t, self.gripper.x_open)
        self._follow(t, approach.waypoints)
        return True

    def _carriable(self, approach: grasp_planner.GraspPlan) -> bool:
        """Whether the object can be carried to the place from `approach`'s grasp."""
        kappas, pose = approach.waypoints[-1]
        try:
            self._plan_carry(np.asarray(kappas, float), float(pose[2]))
        except ValueError:
            return False
        return True

    def _plan_carry(self, start: np.ndarray, heading: float) -> grasp_planner.GraspPlan:
        return plan_carry(
            self.target,
            start,
            heading,
            self.lengths,
            self.base,
            self.lower,
            self.upper,
            self.gripper.geometry,
        )

    def _follow(self, t: float, waypoints: Sequence[tuple[Any, Any]]) -> None:
        """Move through `waypoints` ((curvatures, tip pose) each), then settle on the last."""
        self.waypoints = [(np.asarray(k, float), tuple(p)) for k, p in waypoints]
        self.waypoint = 0
        if not self.waypoints:
            self._enter(t, PHASE["settling"])
            return
        self._move_to(t, self.waypoints[0][0])
        self.phase = PHASE["moving"]

    def _move_to(self, t: float, goal: np.ndarray) -> None:
        goal = np.clip(goal, self.lower, self.upper)
        self.move = CurvatureMove.plan(self.reference, goal, self.rates, self.accel_time)
        self.since = t

    def _enter(self, t: float, phase: int) -> None:
        self.phase = phase
        self.since = t
        self.on_target_since = None
        self.correction = np.zeros(2)
        self.solution = self.reference.copy()

    def _settle(self, t: float, kappa: np.ndarray) -> None:
        """Close the loop on the estimated tip until it has stayed on the leg's last pose for
        settle_time (or max_time has passed), then act on the object (close, open) or finish.
        The curvature loops alone leave the tip centimetres off under the load of a held object
        (small curvature errors add up along the arm): the tip error is integrated into a
        correction of the IK goal (with the plan's heading), as the task-space controller
        does."""
        _, pose = self.waypoints[-1] if self.waypoints else (None, None)
        tip = kinematics.forward(kappa, self.lengths, self.base)[-1, :2]
        error = np.zeros(2)
        if pose is not None and self.leg < 2:
            error = self._close_loop(t, tip, pose)
        if self.leg == 1 and pose is not None:
            self._place(t, error)
            return
        if self._settled(t, pose, error) or t - self.since >= self.plan.max_time:
            self._on_settled(t, kappa, pose)

    def _close_loop(
        self, t: float, tip: np.ndarray, pose: tuple[float, float, float]
    ) -> np.ndarray:
        """One step of the settling loop towards the leg's last pose: the error closed on (the
        carried object's, else the tip's), integrated into the goal's correction once the arm
        has caught up, and the reference moved towards the IK solution of the corrected goal
        within the drives' rates; returns the error."""
        # carrying, the camera sees where the object is (it sits a few millimetres off the
        # nominal grasp point, pressed into the palm): close the loop on it; else on the tip
        error = self.target - self.seen if self.leg == 1 else np.array(pose[:2]) - tip
        lag = np.array(pose[:2]) + self.correction - tip
        # integrate once the arm has caught up; under a load the estimate may keep a bias
        # of a centimetre or two, so after ARRIVAL_TIME in any case
        arrived = t - self.since >= ARRIVAL_TIME
        if float(np.linalg.norm(lag)) <= WINDUP_LIMIT or arrived:
            self.correction += self.plan.task_gain * self.config.control_period * error
            norm = float(np.linalg.norm(self.correction))
            if norm > CORRECTION_LIMIT:
                self.correction *= CORRECTION_LIMIT / norm
        result = solve_ik(
            np.array(pose[:2]) + self.correction,
            self.solution,
            self.lengths,
            self.base,
            self.lower,
            self.upper,
            heading=pose[2],
            heading_weight=HEADING_WEIGHT,
            max_iter=5,
        )
        self.solution = result.kappas
        step = self.rates * self.config.control_period
        self.reference = np.clip(
            self.reference + np.clip(self.solution - self.reference, -step, step),
            self.lower,
            self.upper,
        )
        return error

    def _settled(
        self, t: float, pose: tuple[float, float, float] | None, error: np.ndarray
    ) -> bool:
        """Whether the tip has been within `tolerance` of the leg's last pose (if it has one)
        for settle_time."""
        on_target = pose is None or float(np.linalg.norm(error)) <= self.plan.tolerance
        if on_target:
            if self.on_target_since is None:
                self.on_target_since = t
        else:
            self.on_target_since = None
        return (
            self.on_target_since is not None
            and t - self.on_target_since >= self.plan.settle_time - 1e-9
        )

    def _on_settled(
        self, t: float, kappa: np.ndarray, pose: tuple[float, float, float] | None
    ) -> None:
        """Settled (or out of time): close the fingers on the object (approach), open them
        (carry), or finish (retreat)."""
        if self.leg == 0 and not self._captured(pose):
            self._reapproach(t, kappa)
        elif self.leg == 0:
            self._stroke(t, self.gripper.x_closed)
            self._enter(t, PHASE["grasping"])
        elif self.leg == 1:
            self._stroke(t, self.gripper.x_open)
            self._enter(t, PHASE["releasing"])
        else:
            self._enter(t, PHASE["done"])

    def _reapproach(self, t: float, kappa: np.ndarray) -> None:
        """The approach knocked the object (the arm lags its plan): go round again to where the
        camera sees it now rather than close the fingers on nothing; if the arm is too close to
        it to plan from here, back off first (and plan from there). After MAX_REAPPROACHES the
        task ends where the arm is, the fingers open."""
        if self.reapproaches >= MAX_REAPPROACHES:
            self.note = self.note or "the object is not between the fingers"
            self._enter(t, PHASE["done"])  # nothing to close on: stay, open
            return
        self.reapproaches += 1
        if not self._approach(t, kappa, self.seen) and not self._back_off(t):
            self.reapproaches = MAX_REAPPROACHES

    def _captured(self, pose: tuple[float, float, float] | None) -> bool:
        """Whether fingers closing at the grasp pose `pose` take hold of the object where the
        camera sees it (see CAPTURE_SLACK)."""
        if pose is None:
            return True
        geometry = self.gripper.geometry
        offset = self.seen - grasp_point(geometry, pose)
        axis = np.array([np.cos(pose[2]), np.sin(pose[2])])
        ahead = float(offset @ axis)
        side = float(offset[1] * axis[0] - offset[0] * axis[1])
        room = geometry.root_offset - 0.5 * geometry.finger_width - self.plan.object_radius
        return abs(side) <= room + CAPTURE_SLACK and -CAPTURE_BACK <= ahead <= CAPTURE_AHEAD

    def _place(self, t: float, error: np.ndarray) -> None:
        """When to let go of the carried object (`error`: place location minus its estimated
        centre). The arm pushes the object over the table against its friction, and the soft
        arm stores that push as bending: a segment's bend stiffness is 0.025 N m/rad, and the
        object's friction (15 mN at the tip) with the arm's own table friction bends the base
        by tenths of a radian while the arm moves. Released while still pushing (the object
        creeping at a few mm/s through the tolerance), the arm sprang forward and a finger
        dragged the object 1-2 cm off its place (7 of 20 trials failed so). So the loop settles
        until the object is on target and at rest, where neither pushes the other (the
        friction is regularised: no force, no creep), and only then opens the fingers; at
        max_time it lets go wherever the object is."""
        self.track.append((t, self.seen.copy()))
        while self.track and self.track[0][0] < t - REST_WINDOW - 1e-9:
            self.track.popleft()
        timeout = t - self.since >= self.plan.max_time
        on_target = float(np.linalg.norm(error)) <= self.plan.tolerance
        if not on_target and not timeout:
            self.on_target_since = None
            return
        if self.on_target_since is None:
            self.on_target_since = t
        centres = np.array([c for _, c in self.track])
        spread = float(np.max(np.linalg.norm(centres - self.seen, axis=1)))
        rested = t - self.on_target_since >= REST_WINDOW - 1e-9 and spread <= REST_DRIFT
        if rested or timeout:
            self._stroke(t, self.gripper.x_open)
            self._enter(t, PHASE["releasing"])
