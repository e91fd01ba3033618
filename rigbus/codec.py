"""One DBC message's payload as a `struct.Struct`: values to bytes and back, as cantools does.

The DBC declares each signal's place, width, sign, scale, offset and range. `MessageCodec` reads
them once, when the database is loaded, into a precompiled `struct.Struct` for the payload (one
little-endian field of 1, 2, 4 or 8 bytes per byte-aligned signal, a byte of its own for an
unsigned signal narrower than a byte, pad bytes for the rest) and per signal the constants of
cantools' arithmetic: encoding is ``round((value - offset) / scale)``, decoding
``raw * scale + offset``, each with the scale and offset of the conversion cantools itself uses
(so an identity signal decodes to an int, a float scale to a float), applied to the whole
message at once with `map`. (For an int scale cantools takes ``divmod``'s quotient when the
division is exact: the correctly rounded division gives that same number, for every raw value a
field holds below 2^52.)

Encoding is strict, as cantools' ``encode(..., strict=True)``: a value below its minimum or above
its maximum by more than a millionth of the scale is refused unless its raw value is one the
signal names (its choices), and the FrameError's text after the frame's name is cantools'
own. Before that, the values a frame may carry are made plain: a bool is its int, a sequence
number (`WRAPPING_SIGNALS`) given as an int is taken modulo its range, and a missing value, a
value that is not a number, NaN or an infinity are refused naming the signal. The common frame,
every value a number within its range, takes one comparison per value and no other check.

A layout the struct cannot hold (a signal across byte boundaries, big-endian, a float, a
multiplexed message, a signal without a declared range or whose range does not fit its bits) is
encoded and decoded by cantools itself after the same checks: slower, the same result. Every
message of softhil's DBC has a struct (the tests check it, and check the bytes, values, types and
errors against cantools for every message).

Values travel in the order of their bytes in the payload (`MessageCodec.names`); checks, their
errors and mappings by name follow the DBC's order of the signals. The plain case also runs in C
where it is built (`rigbus.ccodec`, compiled from `MessageCodec.fields`): the same bytes.

Invariant: for every message and every value, `encode` gives the bytes cantools' strict encode
gives or raises FrameError; `decode` gives cantools' ``decode(data, decode_choices=False)``
values, types included.
"""

from __future__ import annotations

import math
import numbers
import operator
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from itertools import repeat
from typing import Any, cast

import cantools
from cantools.database.can import Message
from cantools.database.conversion import BaseConversion

Data = bytes | bytearray  # a frame's payload: python-can gives either

COUNTER_MODULO = 256
WRAPPING_SIGNALS = ("counter", "frame_index")  # sequence numbers: encoded modulo their range
MISSING: Any = object()  # the value of a signal a frame does not have

# struct's little-endian unsigned field codes by width in bytes (the lower case: signed)
_UNSIGNED = {1: "B", 2: "H", 4: "I", 8: "Q"}
_EXACT = 2**52  # below it, every integer and every quotient to round is exact in a double


class FrameError(ValueError):
    """A frame that cannot be encoded or decoded; the message names the frame and CAN id."""


def frame_name(frame_id: int) -> str:
    return f"0x{frame_id:03X}"


def frame_error(message: Message, text: str) -> FrameError:
    """A FrameError that names the message and its CAN id, then says `text`."""
    return FrameError(f"{message.name} ({frame_name(message.frame_id)}): {text}")


class _Signal:
    """What encoding needs of one signal: cantools' conversion constants and checks."""

    def __init__(self, signal: Any) -> None:
        self.name: str = signal.name
        # the conversion cantools applies (its identity conversion keeps ints ints)
        linear = BaseConversion.factory(signal.scale, signal.offset, None, signal.is_float)
        self.scale, self.offset = linear.scale, linear.offset
        # the range cantools enforces: the declared one widened by a millionth of the scale
        tolerance = abs(signal.conversion.scale) * 1e-6
        self.minimum, self.maximum = signal.minimum, signal.maximum
        self.low = -math.inf if signal.minimum is None else signal.minimum - tolerance
        self.high = math.inf if signal.maximum is None else signal.maximum + tolerance
        self.choices = frozenset(signal.choices or ())
        self.modulus: int | None = None
        if signal.name in WRAPPING_SIGNALS:
            self.modulus = int(signal.maximum or COUNTER_MODULO - 1) + 1
        # the quick path's range: cantools' range, and for a sequence number given as an int
        # only the values the modulo leaves alone
        self.quick_low, self.quick_high = self.low, self.high
        if self.modulus is not None:
            self.quick_low, self.quick_high = max(self.low, 0), min(self.high, self.modulus - 1)
        self.start: int = signal.start
        self.length: int = signal.length
        self.signed: bool = signal.is_signed

    def raw(self, value: Any) -> int:
        """cantools' raw value of `value` (a plain number)."""
        return round((value - self.offset) / self.scale)

    def normalised(self, value: Any) -> Any:
        """The number cantools is given for `value`, or FrameError naming the signal (but not
        the message: `MessageCodec` adds it)."""
        if value is MISSING:
            raise FrameError(f"no value for signal {self.name}")
        if not isinstance(value, numbers.Real):
            raise FrameError(f"{self.name} is not a number: {value!r}")
        if isinstance(value, bool):
            return int(value)
        if isinstance(value, int):
            return value if self.modulus is None else value % self.modulus
        if value != value or value in (math.inf, -math.inf):  # NaN or infinite
            raise FrameError(f"{self.name} is {value}")
        return value

    def range_error(self, value: Any, message: str) -> str | None:
        """cantools' text refusing `value` (normalised), None for a value it accepts."""
        if self.choices and math.isfinite(value / self.scale) and self.raw(value) in self.choices:
            return None  # a value the signal names is never out of range
        if value < self.low:
            side = f"greater than or equal to {self.minimum}"
        elif value > self.high:
            side = f"smaller than or equal to {self.maximum}"
        else:
            return None
        return (
            f'Expected signal "{self.name}" value {side} in message "{message}", but got {value}.'
        )


def _layout(message: Message, signals: Sequence[Any]) -> tuple[str, tuple[int, ...]] | None:
    """(struct format, mask of each field: -1 for all its bits) of the message's payload,
    `signals` in the order of their bytes, or None if a struct cannot hold them. Every raw
    value a signal accepts fits its field (`_fits`): a signed raw value is packed as its two's
    complement, a field narrower than its byte leaves the byte's other bits 0, as cantools."""
    if message.is_multiplexed() or message.is_container:
        return None
    layout, masks = ["<"], []
    end = 0  # the first byte no field covers yet
    for s in signals:
        if s.byte_order != "little_endian" or s.is_float or s.start % 8 or s.start // 8 < end:
            return None
        if s.length % 8 == 0 and s.length // 8 in _UNSIGNED:
            width, mask = s.length // 8, -1
        elif s.length < 8 and not s.is_signed:
            width, mask = 1, (1 << s.length) - 1
        else:
            return None
        if not _fits(s):
            return None
        code = _UNSIGNED[width]
        layout.append("x" * (s.start // 8 - end) + (code.lower() if s.is_signed else code))
        masks.append(mask)
        end = s.start // 8 + width
    if end > message.length:
        return None
    return "".join(layout) + "x" * (message.length - end), tuple(masks)


def _fits(signal: Any) -> bool:
    """Whether every raw value the signal accepts (its range, widened as cantools widens it,
    and its choices) fits its bits, and is exact in a double."""
    if signal.minimum is None or signal.maximum is None or signal.scale == 0:
        return False
    spec = _Signal(signal)
    raws = [spec.raw(spec.low), spec.raw(spec.high), *spec.choices]
    if signal.is_signed:
        low, high = -(1 << (signal.length - 1)), (1 << (signal.length - 1)) - 1
    else:
        low, high = 0, (1 << signal.length) - 1
    return low <= min(raws) and max(raws) <= high and max(map(abs, raws)) < _EXACT


@dataclass(frozen=True)
class Field:
    """One value of a `MessageCodec` as its quick path encodes and decodes it: its bits in the
    payload (little-endian, from bit `start`), its conversion (the Python types of the scale and
    offset are those of the decoded value's arithmetic), whether encoding subtracts the offset
    (the codec leaves out offsets that are all 0), the quick range (`low` <= value <=
    `high`; anything else takes the checks), and for a sequence number the modulus an int is
    taken modulo before that (0: none)."""

    name: str
    start: int
    length: int
    signed: bool
    scale: int | float
    offset: int | float
    subtracts_offset: bool
    low: float
    high: float
    modulus: int


def _applied_offsets(signals: Sequence[_Signal]) -> tuple[tuple | None, tuple | None]:
    """The offsets encoding subtracts and decoding adds, None where they are all left out:
    value - 0 is value, and raw * scale + 0 is raw * scale (a positive scale makes no -0.0)."""
    offsets = tuple(s.offset for s in signals)
    if not all(type(o) is int and o == 0 for o in offsets):
        return offsets, offsets
    return None, None if all(s.scale > 0 for s in signals) else offsets


def _field(signal: _Signal, subtracts_offset: bool) -> Field:
    return Field(
        signal.name,
        signal.start,
        signal.length,
        signal.signed,
        signal.scale,
        signal.offset,
        subtracts_offset,
        signal.quick_low,
        signal.quick_high,
        signal.modulus or 0,
    )


def _wrapped(values: Sequence[Any], wraps: tuple[tuple[int, int], ...]) -> Sequence[Any]:
    """`values` with each sequence number given as an int (not a bool) taken modulo its range,
    as the checks take it."""
    wrapped = list(values)
    for k, modulus in wraps:
        if type(wrapped[k]) is int:
            wrapped[k] %= modulus
    return wrapped


class MessageCodec:
    """Encoder and decoder of one DBC message (see the module): `encode(values)` and
    `decode(data)`, the values in the order of `names`, the order of the signals' bytes in the
    payload (`as_mapping` and `values_of` convert from and to a mapping by name).

    Parameters
    ----------
    message
        The message, from a database cantools loaded.
    compiled
        False: cantools encodes and decodes, after the same checks (the reference the tests
        compare the struct with).
    """

    def __init__(self, message: Message, compiled: bool = True) -> None:
        self.message = message
        self.length: int = message.length
        signals = sorted(message.signals, key=lambda s: s.start)
        self.names: tuple[str, ...] = tuple(s.name for s in signals)
        self._signals = [_Signal(s) for s in signals]
        # the positions of the DBC's signals among `names`: the order of checks and mappings
        self._dbc_order = tuple(self.names.index(s.name) for s in message.signals)
        self._scales = tuple(s.scale for s in self._signals)
        self._offsets, self._decode_offsets = _applied_offsets(self._signals)
        self._lows = tuple(s.quick_low for s in self._signals)
        self._highs = tuple(s.quick_high for s in self._signals)
        # the sequence numbers: (position, modulus), an int taken modulo it on the quick path
        self._wraps = tuple(
            (k, s.modulus) for k, s in enumerate(self._signals) if s.modulus is not None
        )
        layout = _layout(message, signals) if compiled else None
        self.compiled = layout is not None  # False: cantools encodes and decodes
        # what the C path compiles (`rigbus.ccodec`): each value's field and quick path
        self.fields = tuple(_field(s, self._offsets is not None) for s in self._signals)
        if layout is not None:
            form, masks = layout
            self._pack = struct.Struct(form).pack
            self._unpack = struct.Struct(form).unpack
            self._masks = None if all(m == -1 for m in masks) else masks

    def encode(self, values: Sequence[Any]) -> bytes:
        """The payload of the signals' `values` (in the order of `names`; `MISSING` for a value
        the frame lacks); FrameError naming the message and signal of a value it refuses."""
        if self.compiled:
            if self._wraps:
                values = _wrapped(values, self._wraps)
            try:
                if all(map(operator.le, self._lows, values)) and all(
                    map(operator.le, values, self._highs)
                ):
                    if self._offsets is not None:
                        values = tuple(map(operator.sub, values, self._offsets))
                    return self._pack(*map(round, map(operator.truediv, values, self._scales)))
            except TypeError:  # not a number: the checks below say which
                pass
        return self._encode_checked(values)

    def _encode_checked(self, values: Sequence[Any]) -> bytes:
        """`encode` with every check, in the DBC's order of the signals: first each value made
        plain (or refused), then each range."""
        message = self.message
        plain = list(values)
        for k in self._dbc_order:
            try:
                plain[k] = self._signals[k].normalised(values[k])
            except FrameError as exc:
                raise frame_error(message, str(exc)) from None
        if not self.compiled:
            numbers_only = [int(v) if isinstance(v, numbers.Integral) else v for v in plain]
            try:
                return message.encode(self.as_mapping(numbers_only), strict=True)
            except (cantools.database.EncodeError, ValueError, KeyError) as exc:
                raise frame_error(message, str(exc)) from exc
        for k in self._dbc_order:
            error = self._signals[k].range_error(plain[k], message.name)
            if error is not None:
                raise frame_error(message, error)
        return self._pack(*(s.raw(v) for s, v in zip(self._signals, plain, strict=True)))

    def decode(self, data: Data) -> tuple[Any, ...]:
        """The signals' values (in the order of `names`) of a payload of `length` bytes."""
        if not self.compiled:
            decoded = self.message.decode(bytes(data), decode_choices=False)
            return tuple(cast(Mapping[str, Any], decoded)[name] for name in self.names)
        raws: Iterable[int] = self._unpack(data)
        if self._masks is not None:
            raws = map(operator.and_, raws, self._masks)
        scaled = map(operator.mul, raws, self._scales)
        if self._decode_offsets is not None:
            scaled = map(operator.add, scaled, self._decode_offsets)
        return tuple(scaled)

    def integral(self) -> tuple[bool, ...]:
        """Whether `decode` gives each signal's value as an int (else a float)."""
        return tuple(type(s.scale) is int and type(s.offset) is int for s in self._signals)

    def values_of(self, signals: Mapping[str, Any]) -> tuple[Any, ...]:
        """The values of a mapping of signal names, in the order of `names` (`MISSING` for a
        signal it lacks)."""
        return tuple(map(signals.get, self.names, repeat(MISSING)))

    def as_mapping(self, values: Sequence[Any]) -> dict[str, Any]:
        """The signals' `values` (in the order of `names`) by name, in the DBC's order."""
        return {self.names[k]: values[k] for k in self._dbc_order}
