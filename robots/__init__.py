"""softhil's robot kinds, one folder each: the plant side (`plant/`: FMUs, device nodes,
connections, markers, signals, checks, metrics, plots), the controller side (`controller`: its
configuration, estimator and controllers), registered together in `rigbus.robots`.

A plant side imports `hil`, `rigbus` and its own controller side (to write the controller's
configuration); a controller side imports `controllers` and `rigbus`, never `hil`.
"""

import rigbus  # noqa: F401  # first: python-can without asammdf (rigbus.pycan)
