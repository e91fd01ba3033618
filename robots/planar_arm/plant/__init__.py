"""The planar arm's plant side: `ROBOT`, its RobotKind (`rig`), with its tasks' metrics
(`tasks`), the environment FMU's part (`environment`), the gripper (`gripper`) and the
animation (`animation`)."""

from robots.planar_arm.plant.rig import ROBOT

__all__ = ["ROBOT"]
