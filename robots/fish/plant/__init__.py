"""The fish's plant side: `ROBOT`, its RobotKind (`rig`), with its device nodes (`devices`),
metrics (`metrics`) and animation (`animation`)."""

from robots.fish.plant.rig import ROBOT

__all__ = ["ROBOT"]
