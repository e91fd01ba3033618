"""repr of floats in C (`_cformat.c`): the signals CSV's rows without a Python call per value.

`hil.recording.SignalRecorder` writes every value of a row as `repr` writes it, so that equal
runs give byte-identical files. repr of a float is CPython's dtoa on big integers, about 0.6 us a
value: with some sixty values a SYNC it was a tenth of the closed loop's instructions.
`format_row` writes the same line in C with the Ryu algorithm (see `_cformat.c`), for a row of
floats and ints, and declines (None) any other row, which the recorder then writes in Python.
The tests check its text against repr on millions of doubles, and its lines against csv.writer.

Ryu needs 128-bit approximations of powers of five and of their inverses. `tables()` computes
them here with Python's exact integers, and the module is compiled from those tables and
`_cformat.c`, with `$CC` (or gcc) against this Python's headers, into the softhil cache. Without
a compiler or the headers, or with ``SOFTHIL_FORMAT=python``, the recorder writes with repr
(`failure()` says why): the files are the same, byte for byte.
"""

from __future__ import annotations

import logging
from pathlib import Path
from types import ModuleType

from rigbus.cbuild import (
    LIBRARY_FLAGS,
    CPart,
    compile_extension,
    load_extension,
)

SOURCE = Path(__file__).with_name("_cformat.c")
MODULE = "_softhil_cformat"
ENV = "SOFTHIL_FORMAT"  # "python": rows written with repr only

# Ryu's double tables: 5^q's inverse for q < 342 (exponents >= 0), 5^i for i < 326 (below 0),
# each the top bits of the exact value as a (low, high) pair of 64-bit words
INV_SIZE, POW_SIZE, INV_BITS, POW_BITS = 342, 326, 125, 125


def tables() -> str:
    """The C definitions of POW5_INV_SPLIT (floor(2^j / 5^q) + 1, j = bits(5^q) - 1 + 125) and
    POW5_SPLIT (5^i shifted to its top 125 bits), exact, from Python's integers."""

    def entry(value: int) -> str:
        assert 0 < value < 1 << 128
        return f"{{{value & (1 << 64) - 1}u, {value >> 64}u}}"

    inverses = []
    for q in range(INV_SIZE):
        power = 5**q
        inverses.append(entry((1 << (power.bit_length() - 1 + INV_BITS)) // power + 1))
    powers = []
    for i in range(POW_SIZE):
        power = 5**i
        shift = power.bit_length() - POW_BITS
        powers.append(entry(power >> shift if shift >= 0 else power << -shift))
    return (
        "#include <stdint.h>\n"
        f"static const uint64_t POW5_INV_SPLIT[{INV_SIZE}][2] = {{\n"
        + ",\n".join(inverses)
        + "\n};\n"
        + f"static const uint64_t POW5_SPLIT[{POW_SIZE}][2] = {{\n"
        + ",\n".join(powers)
        + "\n};\n"
    )


def source() -> str:
    """The module's C source: the tables, then `_cformat.c` (Python.h first, as it requires)."""
    code = SOURCE.read_text()
    head, marker, rest = code.partition("#include <string.h>\n")
    return head + marker + tables() + rest


def _build() -> Path:
    return compile_extension("format", "cformat", source(), LIBRARY_FLAGS)


_part: CPart[ModuleType] = CPart(
    ENV,
    "rows written in C where it builds",
    lambda: load_extension(MODULE, _build),
    logging.getLogger(__name__),
    "signal rows are written by repr in Python (slower, same bytes)",
)


# the C part's interface: `setting()` its variable's value ("c" or "python"; ValueError naming
# it for any other), `load()` the part (built if needed; None if it cannot be) and `failure()`
# why it is not in use (None: it is, or it was not tried yet)
setting = _part.setting
load = _part.get
failure = _part.why
