"""The spatial arm: four (1 to 8) soft segments bending in 3-D under gravity, each with two
antagonistic channel pairs driven by their own drive cylinders; tip positioning, moving to an
object the camera found, shape fitting and advancing through a confined space."""
