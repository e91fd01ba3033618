"""The execution: when the algorithm steps, SYNC by SYNC, and the named step-ahead policy.

The rig's physics must stand at t_c = c T when SYNC(c) is answered (`to_sync`). The commands
that the controller sends during period c are latched by the device nodes at SYNC(c+1) and act
from then on; the nodes' outputs hold between SYNCs (they change only when a node acts, and are
published then). So nothing the controller can send in period c changes how the physics steps
from t_c to t_(c+1), and that stepping may run while the controller computes. The step-ahead
policy says where it runs (`after_sync`):

- `StepAhead.AT_SYNC`: nowhere ahead; `to_sync` steps the whole period when the SYNC comes.
- `StepAhead.IN_TURN`: in this thread right after SYNC(c) is answered, while the controller, in
  another process, computes; `to_sync(c+1)` then finds the physics there.
- `StepAhead.WORKER`: on the C kernel's worker thread, while the controller computes in this
  thread (the direct in-process bus); `to_sync(c+1)` waits for it. The first OVERLAP_PROBES
  periods are stepped in turn and timed: a rig whose period steps in less than
  OVERLAP_MIN_COST goes on AT_SYNC, since waking the worker costs more than it saves.

Invariant: every policy gives the same FMI calls with the same arguments, the same participant
steps and observations, and so the same values bit for bit; an FMU failure while stepping ahead
is held and raised by the next `to_sync`, where stepping at the SYNC would have raised it.
"""

from __future__ import annotations

import enum

from hil.cosim.algorithm import Algorithm
from hil.errors import FmuError

# the periods a WORKER execution steps in turn, timed, before it chooses the worker thread (a
# median of at least OVERLAP_MIN_COST [s] of the kernel's stepping a period) or AT_SYNC
OVERLAP_PROBES = 12
OVERLAP_MIN_COST = 70e-6


class StepAhead(enum.Enum):
    """Where the physics steps to the next SYNC while the controller computes."""

    AT_SYNC = "at SYNC"
    IN_TURN = "in turn"
    WORKER = "worker thread"


class Execution:
    """Steps `algorithm` SYNC by SYNC: period c is ticks c M .. (c+1) M, M = `control_ticks`,
    up to SYNC(`cycles`).

    Parameters
    ----------
    policy
        The step-ahead policy (module docstring).
    spin
        WORKER: how long [s] this thread polls for the worker before it sleeps.
    min_cost
        WORKER: the median kernel time [s] a probed period must take for the worker to pay;
        0: the worker from the first period on.
    """

    def __init__(
        self,
        algorithm: Algorithm,
        control_ticks: int,
        cycles: int,
        policy: StepAhead = StepAhead.AT_SYNC,
        *,
        spin: float = 0.0,
        min_cost: float = OVERLAP_MIN_COST,
    ) -> None:
        self.algorithm = algorithm
        self.control_ticks = control_ticks
        self.cycles = cycles
        self.policy = policy
        self.spin = spin
        self.min_cost = min_cost
        self.periods_on_thread = 0  # periods the FMUs stepped on the kernel's worker thread
        self._held: FmuError | None = None  # what stepping ahead raised, for the next SYNC
        self._costs: list[float] = []  # [s] the probed periods' kernel time (WORKER)

    def to_sync(self, cycle: int) -> None:
        """The physics at SYNC(`cycle`)'s tick: what stepping ahead began is waited for, the rest
        stepped now; an FMU failure held from stepping ahead is raised here."""
        if self._held is not None:
            raise self._held
        self.algorithm.advance_to(cycle * self.control_ticks)

    def after_sync(self, cycle: int) -> None:
        """SYNC(`cycle`) answered: step ahead to the next SYNC by the policy."""
        if self.policy is StepAhead.AT_SYNC or not 0 <= cycle < self.cycles:
            return
        target = (cycle + 1) * self.control_ticks
        try:
            if self.policy is StepAhead.IN_TURN:
                self.algorithm.advance_to(target)
            else:
                self._on_worker(target)
        except FmuError as exc:
            self._held = exc

    def _on_worker(self, target: int) -> None:
        algorithm = self.algorithm
        costs = self._costs
        if self.min_cost > 0.0 and len(costs) < OVERLAP_PROBES:
            # the kernel's share only: Python participants (the camera) step here either way
            before = algorithm.kernel_seconds
            algorithm.advance_to(target)
            costs.append(algorithm.kernel_seconds - before)
            if len(costs) == OVERLAP_PROBES and sorted(costs)[len(costs) // 2] < self.min_cost:
                self.policy = StepAhead.AT_SYNC
        elif algorithm.start_advance(target, self.spin):
            self.periods_on_thread += 1

    def settle(self) -> None:
        """Wait for the worker and stop it: no FMU steps on after the run, nor into a forked
        child."""
        self.algorithm.settle()
