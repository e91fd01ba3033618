"""softhil plant side: FMU build and loading, co-simulation master, device nodes, bus layer, CLI."""

import rigbus  # noqa: F401  # first: python-can without asammdf (rigbus.pycan)
