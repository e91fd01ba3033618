"""rigbus: the protocol both sides of a softhil rig share, and nothing else.

The DBC file (`softhil.dbc`) is the protocol: the frames (`protocol`), their codec (`codec`,
with its C fast path `ccodec`), the bus specs and python-can plumbing (`canbus`), softhil's own
python-can interface and wire format for the loopback hub (`binary`, `wire`) and the build cache
of the C parts (`cbuild`), and python-can itself, imported without asammdf until an MF4 log
needs it (`pycan`: importing any part of softhil imports python-can that way). The plant side
(`hil`) and the controller side (`controllers`) both import it; it imports neither of them, so
a controller program carries no plant code.
"""

from rigbus.pycan import import_can as _import_can

_import_can()
