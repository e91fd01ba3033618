"""rigbus: the protocol both sides of a softhil rig share, and nothing else.

The DBC file (`softhil.dbc`) is the protocol: the frames (`protocol`), their codec (`codec`,
with its C fast path `ccodec`), the bus specs and python-can plumbing (`canbus`), softhil's own
python-can interface and wire format for the loopback hub (`binary`, `wire`) and the build cache
of the C parts (`cbuild`). The plant side (`hil`) and the controller side (`controllers`) both
import it; it imports neither of them, so a controller program carries no plant code.
"""
