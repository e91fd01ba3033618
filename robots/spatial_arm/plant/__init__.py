"""The spatial arm's plant side: `ROBOT`, its RobotKind (`rig`), with its signals (`signals`),
task layout and controller configuration (`task`), checks (`checks`), metrics (`metrics`) and
figures (`figures`)."""

from robots.spatial_arm.plant.rig import SpatialArm

ROBOT = SpatialArm()

__all__ = ["ROBOT"]
