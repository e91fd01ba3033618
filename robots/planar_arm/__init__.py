"""The planar arm: segments bending in the plane of a table, each a fluidic elastomer actuator
pair driven by its own drive cylinder, with an optional gripper, walls, pipes and objects; the
thesis's curvature, point-to-point, path, pipe and grasp-and-place tasks."""
