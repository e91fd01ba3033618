"""softhil plant side: FMU build and loading, co-simulation master, device nodes, bus layer, CLI."""
