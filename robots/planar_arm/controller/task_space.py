"""Task-space control of the planar arm: the main loop above the
per-segment curvature controllers.

Each cycle it reads the estimated curvatures, computes the estimated tip position by the forward
kinematics, and hands every segment a curvature reference:

- point-to-point: for each target, the IK solution (damped least squares,
robots.planar_arm.controller.ik) is
  reached by a realisable curvature move (a synchronised trapezoid within each segment's rate
  limit, robots.planar_arm.controller.tasks.CurvatureMove); then the loop closes on the estimated
  tip: the
  task-space error is integrated (gain `task_gain`, bounded by `correction_limit`) into a
  correction of the IK goal, so that model error between curvature and tip does not stay as a
  tip offset. A target is settled when the estimated tip has stayed within `tolerance` for
  `settle_time`; then the next one begins (after `max_time` it begins anyway).
- path: the tip is first brought to the path's start as a point-to-point target, then a
  reference point moves along the straight line with a trapezoidal speed profile and each cycle
  re-solves the IK from the previous solution (warm start, so the configuration stays continuous),
  with the same integrated correction; then it settles on the end point.

The curvature references always stay within each segment's reachable range (from its physics at
full stroke) and their rate within what the drive can follow. A TaskState frame each cycle
reports the target (or path) index, the phase and the task-space reference point, for recording
and scoring.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from controllers import kinematics
from controllers.estimation import DriveReading, Estimate
from rigbus.protocol import ControllerState, DriveCommand, Protocol, TaskState
from robots.planar_arm.controller.curvature_control import CurvatureControl
from robots.planar_arm.controller.ik import MAX_ITER, solve_ik
from robots.planar_arm.controller.tasks import PHASE, CurvatureMove, path_timing, trapezoid_fraction

if TYPE_CHECKING:
    from robots.planar_arm.controller.config import ControllerConfig

TRACK_IK_ITERATIONS = 5  # warm-started DLS iterations per cycle while the goal moves


class TaskSpaceControl:
    """Point-to-point and path tasks over the per-segment curvature PIs; see the module."""

    def __init__(self, config: ControllerConfig, protocol: Protocol) -> None:
        if config.plan is None:
            raise ValueError("plan: task-space control needs a task plan")
        self.config = config
        self.plan = config.plan
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
        self.T = config.control_period
        self.reference = np.zeros(config.segments)  # curvature references handed to the PIs
        self.solution = np.zeros(config.segments)  # the last IK solution (warm start)
        self.correction = np.zeros(2)  # integrated task-space correction of the goal [m]
        self.leg = 0
        self.phase = PHASE["idle"]
        self.leg_start = 0.0
        self.on_target_since: float | None = None
        self.move: CurvatureMove | None = None
        self.goal = np.array(self.plan.targets[0]) if self.plan.targets else np.zeros(2)
        self.tracking = False  # path task: on the line (else approaching its start)
        self.path_timing = (0.0, 0.0)  # (duration, ramp) [s] of the current path's traverse
        self.waypoints: list[np.ndarray] = []  # pipe: the whole-arm plan's configurations
        # pipe: the plan (robots.planar_arm.controller.confined_planner.Plan)
        self.planned: Any = None
        self.notes: list[str] = []  # for the run's summary (ControllerReport.notes)

    # ------------------------------------------------------------------ the cycle

    def compute(
        self, cycle: int, t: float, estimate: Estimate, drives: Mapping[int, DriveReading]
    ) -> list[Any]:
        tip = kinematics.forward(estimate.kappa, self.lengths, self.base)[-1, :2]
        if self.phase == PHASE["idle"] and t < self.plan.acquire_time - 1e-9:
            # the estimator is still acquiring the arm (its prior is the straight arm): hold every
            # piston where it is, and report the estimate as the reference
            return self._hold(cycle, estimate, drives)
        if self.phase == PHASE["idle"] and self.plan.kind == "pipe":
            self._plan_pipe(t, np.asarray(estimate.kappa, float))
        elif self.phase == PHASE["idle"]:
            self._begin_leg(t, from_kappa=np.asarray(estimate.kappa, float))
        elif self.phase == PHASE["done"] and self.waypoints:
            pass  # a pipe's last waypoint stays the reference
        elif self.phase == PHASE["done"]:  # hold the last target, still closing the loop
            self._correct(self.goal - tip)
            self._solve(self.goal + self.correction, iterations=TRACK_IK_ITERATIONS)
        else:
            self._advance(t, tip)
        moving = self.phase == PHASE["moving"] and self.move is not None
        motion = self.move.motion(t - self.leg_start) if moving and self.move else None
        frames = self.curvature.command(cycle, self.reference, estimate, drives, motion)
        index = self.leg if self.waypoints else min(self.leg, self.plan.legs() - 1)
        frames.append(
            TaskState(index, self.phase, float(self.goal[0]), float(self.goal[1]), cycle % 256)
        )
        return frames

    def _hold(
        self, cycle: int, estimate: Estimate, drives: Mapping[int, DriveReading]
    ) -> list[Any]:
        frames: list[Any] = []
        for i in range(self.config.segments):
            node = i + 1
            reading = drives.get(node)
            piston = reading.piston_position if reading is not None else self.config.x_mid[i]
            lo, hi = self.curvature.shown_range  # an estimate still settling may exceed it
            kappa = min(max(float(estimate.kappa[i]), lo), hi)
            frames.append(DriveCommand(node, piston, True, cycle))
            frames.append(ControllerState(node, kappa, kappa, cycle))
        goal = self.plan.targets[0]
        frames.append(TaskState(0, PHASE["idle"], goal[0], goal[1], cycle % 256))
        return frames

    def _advance(self, t: float, tip: np.ndarray) -> None:
        tau = t - self.leg_start
        if self.phase == PHASE["moving"] and self.move is not None:
            self.reference = self.move.value(tau)
            if tau >= self.move.duration and self.waypoints and self.leg + 1 < len(self.waypoints):
                self.leg += 1  # the next waypoint of the whole-arm plan, without stopping
                self.leg_start = t
                self.move = CurvatureMove.plan(
                    self.reference,
                    self.waypoints[self.leg],
                    self.rates,
                    self.accel_time,
                )
            elif tau >= self.move.duration:
                self.phase = PHASE["settling"]
                self.on_target_since = None
        elif self.phase == PHASE["tracking"]:
            self._track(t, tip)
        elif self.phase == PHASE["settling"]:
            self._settle(t, tip)
        elif self.phase == PHASE["settled"]:
            self._next_leg(t)
            return
        # give up on a target that does not settle (a path's traverse has its own duration)
        waited = t - self.leg_start  # the traverse restarts the clock for its end point
        if self.phase in (PHASE["moving"], PHASE["settling"]) and waited > self.plan.max_time:
            self._next_leg(t)

    def _settle(self, t: float, tip: np.ndarray) -> None:
        """Close the loop on the estimated tip until it stays on target for settle_time."""
        error = self.goal - tip
        if not self.waypoints:  # in a pipe the plan's last waypoint is held: an unconstrained
            # IK correction would move the body into the walls the plan keeps it from
            self._correct(error)
            self._solve(self.goal + self.correction, iterations=None)
        if np.linalg.norm(error) <= self.plan.tolerance:
            if self.on_target_since is None:
                self.on_target_since = t
            elif t - self.on_target_since >= self.plan.settle_time - 1e-9:
                self.phase = PHASE["settled"]  # reported for one cycle, then the next leg
        else:
            self.on_target_since = None

    def _track(self, t: float, tip: np.ndarray) -> None:
        """Path task: the reference point moves along the line; IK warm-started each cycle."""
        start, end = np.array(self.plan.targets[self.leg]), np.array(self.plan.ends[self.leg])
        duration, ramp = self.path_timing
        tau = t - self.leg_start
        self.goal = start + (end - start) * trapezoid_fraction(tau, duration, ramp)
        self._correct(self.goal - tip)
        self._solve(self.goal + self.correction, iterations=TRACK_IK_ITERATIONS)
        if tau >= duration:  # the reference has arrived: settle on the end point
            self.phase = PHASE["settling"]
            self.leg_start = t
            self.on_target_since = None

    # ------------------------------------------------------------------ legs

    def _begin_leg(self, t: float, from_kappa: np.ndarray | None = None) -> None:
        """Start target (or path) `self.leg`: a realisable move to the IK solution of its
        target (or its path's start)."""
        self.leg_start = t
        self.tracking = False
        self.correction[:] = 0.0
        self.on_target_since = None
        self.goal = np.array(self.plan.targets[self.leg])
        start = (
            self.reference if from_kappa is None else np.clip(from_kappa, self.lower, self.upper)
        )
        if from_kappa is not None:
            self.reference = start.copy()
            self.solution = start.copy()
        self.solution = self._configuration_for(self.goal, start)
        self.move = CurvatureMove.plan(start, self.solution, self.rates, self.accel_time)
        self.phase = PHASE["moving"]

    def _plan_pipe(self, t: float, estimated: np.ndarray) -> None:
        """Confined space: plan the whole arm's way through the channel from the estimated
        configuration (robots.planar_arm.controller.confined_planner), then track its waypoints by
        curvature moves and settle on the goal."""
        from robots.planar_arm.controller.confined import Channel
        from robots.planar_arm.controller.confined_planner import plan_whole_arm

        start = np.clip(estimated, self.lower, self.upper)
        channel = Channel(self.plan.walls, self.plan.centreline)
        self.goal = np.array(self.plan.targets[0])
        result = plan_whole_arm(
            start,
            self.goal,
            self.lengths,
            self.base,
            self.lower,
            self.upper,
            channel,
            width=self.plan.width,
            margin=self.plan.clearance,
        )
        self.planned = result
        if result.slack_steps:
            self.notes.append(
                f"the pipe plan cannot keep the {self.plan.clearance * 1e3:g} mm clearance from "
                f"the walls at {len(result.slack_steps)} of its {len(result.configurations) - 1} "
                f"steps (first: step {result.slack_steps[0]}) and relaxes it there"
            )
        if not result.reached:
            self.notes.append(f"the pipe plan falls short of the goal: {result.reason}")
        self.waypoints = [np.asarray(k, float) for k in result.configurations[1:]] or [start]
        self.reference = start.copy()
        self.solution = self.waypoints[-1].copy()
        self.leg, self.leg_start = 0, t
        self.move = CurvatureMove.plan(start, self.waypoints[0], self.rates, self.accel_time)
        self.phase = PHASE["moving"]

    def _next_leg(self, t: float) -> None:
        if self.waypoints:  # the pipe's one goal is settled (or given up on)
            self.phase = PHASE["done"]
            return
        if self.plan.kind == "path" and not self.tracking and self.leg < self.plan.legs():
            # the start is reached: traverse the line
            self.tracking = True
            self.leg_start = t
            self.on_target_since = None
            start, end = np.array(self.plan.targets[self.leg]), np.array(self.plan.ends[self.leg])
            self.path_timing = path_timing(
                float(np.linalg.norm(end - start)), self.plan.speed, self.plan.acceleration
            )
            self.phase = PHASE["tracking"]
            return
        self.leg += 1
        if self.leg >= self.plan.legs():
            self.phase = PHASE["done"]  # hold the last reference
            return
        self._begin_leg(t)

    # ------------------------------------------------------------------ helpers

    def _configuration_for(self, goal: np.ndarray, current: np.ndarray) -> np.ndarray:
        """The IK solution for a new target: the bounded DLS is local, and from the previous
        target's configuration it can stall against a bound far from a target on the other
        side; so it also starts from the least-bent configuration and from each half of the
        range, and takes the converged solution nearest the current curvatures (the shortest
        move), else the one that comes closest."""
        starts = [current, np.zeros_like(current), 0.5 * self.lower, 0.5 * self.upper]
        best, best_key = None, (True, math.inf, math.inf)
        for initial in starts:
            result = solve_ik(goal, initial, self.lengths, self.base, self.lower, self.upper)
            key = (
                not result.converged,
                0.0 if result.converged else result.position_error,
                float(np.max(np.abs((result.kappas - current) / self.rates))),
            )
            if key < best_key:
                best, best_key = result.kappas, key
        assert best is not None
        return best

    def _correct(self, error: np.ndarray) -> None:
        """Integrate the estimated tip error into the goal's correction, only while the error
        is within the correction's bound: while the arm is still on its way (tens of mm behind
        its reference) integrating would wind the correction up to its bound, and unwinding it
        would cost seconds of settling."""
        if float(np.linalg.norm(error)) > self.plan.correction_limit:
            return
        self.correction += self.plan.task_gain * self.T * error
        norm = float(np.linalg.norm(self.correction))
        if norm > self.plan.correction_limit:
            self.correction *= self.plan.correction_limit / norm

    def _solve(self, goal: np.ndarray, iterations: int | None) -> None:
        """Move the reference towards the IK solution of `goal` within the rate limits."""
        result = solve_ik(
            goal,
            self.solution,
            self.lengths,
            self.base,
            self.lower,
            self.upper,
            max_iter=MAX_ITER if iterations is None else iterations,
        )
        self.solution = result.kappas
        step = np.clip(result.kappas - self.reference, -self.rates * self.T, self.rates * self.T)
        self.reference = np.clip(self.reference + step, self.lower, self.upper)
