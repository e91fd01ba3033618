"""The spatial arm's controller side: its model (kinematics, statics, inverse kinematics)."""
