"""The DBC codec's plain case in C (`_ccodec.c`): the one fast path of `rigbus.codec`.

`rigbus.protocol.Protocol` encodes and decodes through it when it is available: a frame's
values to bytes and a payload to its typed frame in one C call each, and the `can.Message`s
made in C too (`rigbus.canbus.c_messages`). It handles the plain case only (every value a float,
or an int for a signal without scale and offset, within the codec's quick range; a payload whose
index matches) and returns None for anything else, which the codec's Python path then encodes or
refuses with its error: results and errors are the same bit for bit (tests/test_ccodec.py).

It pays (bench/bench_codec.py; callgrind for the instructions): a DriveStatus is encoded in
0.79 us and decoded in 0.32 us (7.1 and 3.3 thousand instructions) against 2.8 and 2.7 us (25 and
24 thousand) in the Python path; a 6-segment SYNC's frames, some 27 each way, in 28 us against
129 us, a quarter of a SYNC of a quiet hour (370-400 us), and 0.27 against 1.15 million of the
SYNC's 2.9 million instructions.

The module is compiled with `$CC` (or gcc) against this Python's headers into the softhil cache
(`rigbus.cbuild`, shared with the plant's kernel: the controller never imports `hil`),
keyed by a digest of the source, the flags, the compiler and the Python ABI, and loaded from
there. Without a compiler or the headers, or with ``SOFTHIL_CODEC=python``, the Python path does
everything (`failure()` says why).
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
from pathlib import Path
from types import ModuleType
from typing import Any

from rigbus.cbuild import (
    LIBRARY_FLAGS,
    CPart,
    compile_extension,
    load_extension,
)
from rigbus.codec import MessageCodec

SOURCE = Path(__file__).with_name("_ccodec.c")
MODULE = "_softhil_ccodec"
FLAGS = LIBRARY_FLAGS
ENV = "SOFTHIL_CODEC"  # "python": never use the C codec
KINDS = {"float": 0, "int": 1, "bool": 2}  # a field's converter, as _ccodec.c numbers them


def _build() -> Path:
    """The module in the softhil cache, compiled if it is not there (CompileError if it cannot
    be: no compiler, no Python.h, a compiler error)."""
    return compile_extension("codec", "ccodec", SOURCE, FLAGS)


_part: CPart[ModuleType] = CPart(
    ENV,
    "the C codec where it builds",
    lambda: load_extension(MODULE, _build),
    logging.getLogger(__name__),
    "the DBC codec runs in Python only (slower, same frames)",
)


# the C part's interface: `setting()` its variable's value ("c" or "python"; ValueError naming
# it for any other), `load()` the part (built if needed; None if it cannot be) and `failure()`
# why it is not in use (None: it is, or it was not tried yet)
setting = _part.setting
load = _part.get
failure = _part.why


def encoder(codec: MessageCodec) -> Any | None:
    """The C encoder of `codec`'s plain case (for `pack(encoder, values)`), None if there is
    none: no C module, or a message the codec leaves to cantools."""
    module = load()
    if module is None or not codec.compiled:
        return None
    plan = tuple(
        (
            f.start,
            (1 << f.length) - 1,
            _identity(f.scale, f.offset),
            f.scale,
            not f.subtracts_offset or (type(f.offset) is int and f.offset == 0),
            f.offset,
            f.low,
            f.high,
            *_raw_range(f.length, f.signed),
            f.modulus,
        )
        for f in codec.fields
    )
    try:
        return module.compile_encoder(codec.length, plan)
    except (ValueError, TypeError, OverflowError):
        return None


def decoder(
    codec: MessageCodec,
    cls: type,
    kinds: dict[str, str],
    index_field: str | None,
    index: int | None,
) -> Any | None:
    """The C decoder of `codec`'s payloads into frames of `cls` (for `unpack(decoder, data)`),
    each signal's value through its field's converter (`kinds` by name: "float", "int" or
    "bool", float(v), int(v) or bool(int(v))) and the index field `index_field` set to `index`;
    None if there is none: no C module, a message the codec leaves to cantools, or a class whose
    instance is more than its fields' slots (the C decoder fills them, as the dataclass's
    `__init__` does)."""
    module = load()
    if module is None or not codec.compiled or not _plain_slots(cls):
        return None
    names = [f.name for f in dataclasses.fields(cls)]
    try:
        plan = tuple(
            (
                f.start,
                (1 << f.length) - 1,
                f.length,
                f.signed,
                _identity(f.scale, f.offset),
                f.scale,
                f.offset,
                KINDS[kinds[f.name]],
                names.index(f.name),
            )
            for f in codec.fields
        )
        position = -1 if index_field is None else names.index(index_field)
        return module.compile_decoder(codec.length, cls, tuple(names), index, position, plan)
    except (KeyError, ValueError, TypeError, OverflowError):
        return None


def _identity(scale: float, offset: float) -> bool:
    """Whether the conversion leaves the raw value as it is (an int scale of 1, offset 0)."""
    return type(scale) is int and scale == 1 and type(offset) is int and offset == 0


def _raw_range(length: int, signed: bool) -> tuple[int, int]:
    """(lowest, highest) raw value of a field of `length` bits."""
    if signed:
        return -(1 << (length - 1)), (1 << (length - 1)) - 1
    return 0, (1 << length) - 1


def _plain_slots(cls: type) -> bool:
    """Whether an instance of `cls` is its dataclass fields' slots and nothing more: what its
    `__init__` makes is what the C decoder makes."""
    if not dataclasses.is_dataclass(cls) or "__slots__" not in vars(cls):
        return False
    names = [f.name for f in dataclasses.fields(cls)]
    return (
        not hasattr(cls, "__post_init__")
        and cls.__new__ is object.__new__
        and type(cls) is type
        # every field, and nothing else (an InitVar, say), is an argument of `__init__`
        and list(inspect.signature(cls).parameters) == names
    )
