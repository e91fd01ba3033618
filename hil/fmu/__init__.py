"""FMU sources to FMUs (build), and FMUs to co-simulation participants (fmpy)."""
