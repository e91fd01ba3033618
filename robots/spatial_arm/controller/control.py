"""The spatial arm's controller: plans each goal's bends (spatial IK on the gravity-loaded static
model, or shape fitting), moves to them along a realisable trapezoidal bend-velocity profile, and
tracks the profile with a cascade: the static inverse (the pistons that hold the reference under
gravity) as the feedforward, a PI from bend error to the piston setpoints around it (its gains,
`kp` and `ki` in the configuration, are zero by default: the feedforward is exact where the
controller's model is the arm, and the estimate's bend noise would only wander the pistons; the
task-space correction below closes the loop on the well-observed tip instead), and a
derivative part on the estimated bend rates that damps the arm's slow modes (the elastomer
alone leaves them at a damping ratio near 0.05: a move would ring for seconds); the drive's
position servo is the inner loop. Answers each cycle with a
DriveCommand and a ControllerState frame per drive and a SpatialTaskState frame.

Phases (SpatialTaskState.phase, TaskState's values): 0 idle (waiting for the object's marker),
1 moving (on the profile), 2 settling (the profile is done: the estimate is not yet within the
tolerance), 3 settled (it stayed within it for `settle_time`: next goal), 4 done. A goal not
settled within `max_time` of its start is given up (the metrics count it as missed).

In settling, a slow task-space loop moves the bend target by the tip Jacobian's damped
pseudo-inverse times the estimated tip error (TASK_GAIN per second): the static model and the
arm agree in this rig, but where they do not (another arm body, a payload) the tip still arrives.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.estimation import DriveReading
from rigbus.protocol import ControllerState, DriveCommand, Protocol, SpatialTaskState
from robots.spatial_arm.controller import dynamics, kinematics, statics
from robots.spatial_arm.controller.config import SpatialConfig
from robots.spatial_arm.controller.estimator import SpatialEstimate
from robots.spatial_arm.controller.markers import Markers
from robots.spatial_arm.controller.model import ArmModel

IDLE, MOVING, SETTLING, SETTLED, DONE = range(5)
TASK_GAIN = 0.5  # [1/s] the task-space correction's rate in settling
DAMPING = 1e-3  # [m] of the damped pseudo-inverse
DAMPING_RATIO = 0.5  # the slow modes' damping the drives add (the elastomer alone: about 0.05)
DAMPED_BELOW = 3.0  # [Hz] modes the loop damps: its delays (camera, period) leave the faster
OBJECT_FRAMES = 5  # pictures of the object averaged before its goal is planned


@dataclass(frozen=True)
class Trapezoid:
    """A move from q0 to q1 with every coordinate on one normalised trapezoidal profile: the
    coordinate that moves most reaches `speed` and `acceleration`, the others scale with it."""

    t0: float
    q0: np.ndarray
    q1: np.ndarray
    t_acc: float
    t_total: float

    @classmethod
    def plan(
        cls, t0: float, q0: np.ndarray, q1: np.ndarray, speed: float, acceleration: float
    ) -> Trapezoid:
        distance = float(np.max(np.abs(q1 - q0))) if len(q0) else 0.0
        if distance <= 0.0:
            return cls(t0, q0, q1, 0.0, 0.0)
        t_acc = speed / acceleration
        if acceleration * t_acc**2 >= distance:  # triangular: never reaches the speed
            t_acc = math.sqrt(distance / acceleration)
            return cls(t0, q0, q1, t_acc, 2.0 * t_acc)
        return cls(t0, q0, q1, t_acc, distance / speed + t_acc)

    def share(self, t: float) -> float:
        """The share of the move done at `t`, 0 to 1."""
        if self.t_total <= 0.0:
            return 1.0
        s = min(max(t - self.t0, 0.0), self.t_total)
        ta, tt = self.t_acc, self.t_total
        peak = 1.0 / (tt - ta)  # normalised speed
        if s < ta:
            return 0.5 * peak / ta * s * s
        if s <= tt - ta:
            return peak * (s - 0.5 * ta)
        r = tt - s
        return 1.0 - 0.5 * peak / ta * r * r

    def at(self, t: float) -> np.ndarray:
        return self.q0 + self.share(t) * (self.q1 - self.q0)

    def done(self, t: float) -> bool:
        return t >= self.t0 + self.t_total


class SpatialControl:
    def __init__(self, config: SpatialConfig, model: ArmModel, protocol: Protocol) -> None:
        self.config = config
        self.model = model
        self.n_q = model.n_q
        self.lengths = np.repeat(np.asarray(model.L), 2)
        self.markers = Markers(model)
        self.q_ref = np.asarray(config.start, dtype=float)
        self.q_goal = self.q_ref.copy()
        self.move: Trapezoid | None = None
        self.integral = np.zeros(self.n_q)
        self.x_goal = np.full(self.n_q, model.x_seal)  # the feedforward at the goal
        self.x_from = self.x_goal.copy()
        self._gains(self.q_ref, self.x_goal)
        self.feedforward = self.x_goal
        self.phase = IDLE
        self.index = 0
        self.goal_start = 0.0
        self.on_target_since: float | None = None
        self.target = np.full(3, math.nan)
        self.goals = [np.asarray(g, dtype=float) for g in config.goals]
        self.stations: list[np.ndarray] = []  # the confined task's plan
        self.bend_steps = [np.asarray(step[1:], dtype=float) for step in config.bends]
        self.step_times = [float(step[0]) for step in config.bends]
        self.shown_range = protocol.signal_range("ControllerState1", "kappa_est")

    def _gains(self, q: np.ndarray, x: np.ndarray) -> None:
        """At the rest (q, x): `gain`, dx/dq of the static inverse [m/rad], the matrix
        diag(dtau/dx)^-1 H, H the static stiffness (bending, gravity, gas): gravity couples the
        coordinates, so the PI's correction of one bend moves the pistons that hold the others
        too; and `damping`, the pistons per bend rate [m s/rad] that add the torque -C q' with
        C the modal damping of the slow modes (`dynamics.modal_damping`)."""
        H = statics.stiffness(self.model, q, x)
        d_x = statics.gas_torque(self.model, q, x).d_x
        self.gain = np.asarray(H / d_x[:, None], dtype=float)
        M = dynamics.mass_matrix(self.model, q)
        C = dynamics.modal_damping(M, H, DAMPING_RATIO, 2.0 * math.pi * DAMPED_BELOW)
        self.damping = np.asarray(C / d_x[:, None], dtype=float)

    # ------------------------------------------------------------------ planning

    def _plan_goal(self, t: float, estimate: SpatialEstimate) -> bool:
        """Plan the next goal's bends; False when there is none yet (the object's marker not
        seen enough, the next configuration step not due)."""
        kind = self.config.task
        if kind != "configuration":
            from robots.spatial_arm.controller import ik  # the planner of the tasks with goals
        if kind == "confined":
            goal = self._station(estimate)
        elif kind == "point":
            self.target = self.goals[self.index]
            goal = ik.solve_ik(self.model, self.target, start=estimate.q).q
        elif kind == "object":
            if estimate.object_frames < OBJECT_FRAMES:
                return False
            self.target = estimate.object + np.asarray(self.config.offset)
            goal = ik.solve_ik(self.model, self.target, start=estimate.q).q
        elif kind == "shape":
            curve = np.asarray(self.config.curve, dtype=float)
            self.target = curve[-1]
            goal = ik.fit_shape(self.model, curve, start=estimate.q).q
        else:  # configuration
            if t < self.step_times[self.index]:
                return False
            goal = self.bend_steps[self.index]
            self.target = kinematics.tip(self.model, goal)
        self.q_goal = np.asarray(goal, dtype=float)
        self.move = Trapezoid.plan(
            t, self.q_ref.copy(), self.q_goal, self.config.speed, self.config.acceleration
        )
        # the feedforward moves on the same profile, from where it is to the goal's pistons
        self.x_from = self.x_goal.copy()
        pistons = statics.pistons_for(self.model, self.q_goal).x
        self.x_goal = np.where(np.isfinite(pistons), pistons, self.x_from)
        self._gains(self.q_goal, self.x_goal)
        self.goal_start = t
        self.on_target_since = None
        self.phase = MOVING
        return True

    def _station(self, estimate: SpatialEstimate) -> np.ndarray:
        """The confined task's next station (the whole plan made at the first)."""
        from robots.spatial_arm.controller import confined

        c = self.config
        pipe = confined.Pipe(np.asarray(c.pipe, dtype=float), c.pipe_radius)
        if not self.stations:
            self.stations = confined.plan_insertion(
                self.model, pipe, c.goal_depth, c.width, c.clearance, c.insertion_step, estimate.q
            )
        q = self.stations[self.index]
        self.target = kinematics.tip(self.model, q)
        return q

    def _error(self, estimate: SpatialEstimate) -> float:
        """How far from the goal: the tip's distance [m], or for a shape or a configuration the
        largest bend error times its segment's length [m]."""
        if self.config.task in ("point", "object", "confined"):
            return float(np.linalg.norm(estimate.tip - self.target))
        return float(np.max(np.abs(estimate.q - self.q_goal) * self.lengths[: self.n_q]))

    def _advance(self, t: float, estimate: SpatialEstimate) -> None:
        if self.phase == SETTLED:
            self.index += 1
            self.phase = IDLE
        if self.phase == IDLE:
            if self._finished():
                self.phase = DONE
                return
            if not self._plan_goal(t, estimate):
                return  # the object not seen enough yet, or the next step not due
        if self.phase == MOVING and self.move is not None and self.move.done(t):
            self.phase = SETTLING
        if self.phase == SETTLING:
            self._settle(t, estimate)

    def _finished(self) -> bool:
        kind = self.config.task
        if kind == "point":
            return self.index >= len(self.goals)
        if kind == "confined":
            return bool(self.stations) and self.index >= len(self.stations)
        if kind == "configuration":
            return self.index >= len(self.bend_steps)
        return self.index >= 1

    def _settle(self, t: float, estimate: SpatialEstimate) -> None:
        error = self._error(estimate)
        if error <= self.config.tolerance:
            if self.on_target_since is None:
                self.on_target_since = t
            elif t - self.on_target_since >= self.config.settle_time - 1e-9:
                self.phase = SETTLED
                return
        else:
            self.on_target_since = None
        next_step = self.index + 1
        if t - self.goal_start >= self.config.max_time or (
            next_step < len(self.step_times) and t >= self.step_times[next_step]
        ):
            self.phase = SETTLED  # given up, or the next step is due: the metrics judge it
            return
        if self.config.task in ("point", "object", "confined"):
            self._task_space(estimate)

    def _task_space(self, estimate: SpatialEstimate) -> None:
        """Nudge the bend target along the damped pseudo-inverse of the tip Jacobian."""
        J = self.markers(estimate.q)[1][-1]
        e = self.target - estimate.tip
        JJt = J @ J.T + DAMPING**2 * np.eye(3)
        step = J.T @ np.linalg.solve(JJt, e) * TASK_GAIN * self.config.control_period
        pistons = self.x_goal + self.gain @ step
        if np.all((pistons >= self.config.x_min) & (pistons <= self.config.x_max)):
            self.q_goal = self.q_goal + step
            self.x_goal = pistons

    # ------------------------------------------------------------------ each cycle

    def compute(
        self,
        cycle: int,
        t: float,
        estimate: SpatialEstimate,
        drives: Mapping[int, DriveReading],
    ) -> list[Any]:
        self._advance(t, estimate)
        if self.phase == MOVING and self.move is not None:
            share = self.move.share(t)
            self.q_ref = self.move.q0 + share * (self.move.q1 - self.move.q0)
            self.feedforward = self.x_from + share * (self.x_goal - self.x_from)
        elif self.phase in (SETTLING, SETTLED, DONE):
            self.q_ref = self.q_goal.copy()
            self.feedforward = self.x_goal
        return self.command(cycle, estimate, drives)

    def command(
        self, cycle: int, estimate: SpatialEstimate, drives: Mapping[int, DriveReading]
    ) -> list[Any]:
        c = self.config
        error = self.q_ref - estimate.q
        trial = self.integral + error * c.control_period
        raw = (
            self.feedforward
            + self.gain @ (c.kp * error + c.ki * trial)
            - self.damping @ estimate.q_rate
        )
        setpoints = np.clip(raw, c.x_min, c.x_max)
        # no wind-up against a saturated stroke: the integral grows only where it is not
        self.integral = np.where(setpoints == raw, trial, self.integral)
        frames: list[Any] = []
        lo, hi = self.shown_range
        for j in range(self.n_q):
            node = j + 1
            setpoint = float(setpoints[j])
            length = self.lengths[j]
            frames.append(DriveCommand(node, setpoint, True, cycle))
            frames.append(
                ControllerState(
                    node,
                    min(max(self.q_ref[j] / length, lo), hi),
                    min(max(estimate.q[j] / length, lo), hi),
                    cycle,
                )
            )
        x, y, z = (float(v) if math.isfinite(v) else 0.0 for v in self.target)
        frames.append(SpatialTaskState(self.index % 256, self.phase, x, y, z))
        return frames
