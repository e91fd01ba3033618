"""Bus tools behind `hil bus`: log reading/writing, dump, record, replay, send, load, vcan.

Each module does one job and raises `HilError` subclasses for anything a user can cause; the
CLI (`hil.cli.bus`) only parses arguments and calls them.
"""
