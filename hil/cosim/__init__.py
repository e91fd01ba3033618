"""The co-simulation core, shaped as libcosim's: participants, one algorithm, an execution,
observers.

- `participant`: what is stepped (`Participant`, `FmuParticipant`), what watches (`Observer`),
  and how outputs reach inputs (`Connection`).
- `algorithm`: fixed-step Jacobi stepping with integer time; its inner loop in C (`kernel`),
  its Python path the test oracle.
- `execution`: SYNC by SYNC, with the named step-ahead policy (`StepAhead`).

The core knows no robot and no bus: the plant (`hil.plant`) drives it from the CAN protocol.
"""

from hil.cosim.algorithm import Algorithm
from hil.cosim.execution import Execution, StepAhead
from hil.cosim.participant import Connection, FmuParticipant, Observer, Participant

__all__ = [
    "Algorithm",
    "Connection",
    "Execution",
    "FmuParticipant",
    "Observer",
    "Participant",
    "StepAhead",
]
