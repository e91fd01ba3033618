"""softhil controller side: kinematics, estimators, control laws and the controller node.

Never imports `hil`: the controller sees the rig only through the CAN bus.
"""

import rigbus  # noqa: F401  # first: python-can without asammdf (rigbus.pycan)
