"""The error hierarchy of softhil: one clear line for the user, with the context that locates it.

Every error a user can cause (a bad scenario, a corrupt log, an unknown CAN id, a dead controller,
an FMU that fails) is raised as a subclass of `HilError`; the CLI prints `str(error)` as one line
and exits non-zero, and shows the traceback only with `--debug`.
"""


class HilError(Exception):
    """Base of every error softhil reports to its user."""


class BuildError(HilError):
    """An FMU could not be generated, compiled or packed."""


class FmuError(HilError):
    """An FMU rejected a call (instantiation, initialisation, a step, a value)."""


class ScenarioError(HilError):
    """A scenario file is malformed or impossible: names the file, the key and the reason."""


class BusError(HilError):
    """A CAN transport, frame or protocol problem: names the CAN id or the transport."""


class ProtocolError(BusError):
    """The lockstep protocol was violated: a missing, late or stale frame, or a dead peer."""


class ReplayError(HilError):
    """A log that cannot be replayed (no SYNC, counters out of order, ids not in the DBC)."""


class Terminated(BaseException):
    """SIGTERM arrived (a CI runner or container stopping us): unwinds like KeyboardInterrupt,
    closing files and writing summary.json, and exits 143."""
