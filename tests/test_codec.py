"""rigbus.codec against cantools, its oracle: for every message of softhil's DBC and for DBCs
with offsets and layouts a struct cannot hold, the same bytes as cantools' strict encode, the
same values (and types) as its decode, and the same refusals, with cantools' own text after
the frame's name; values drawn by hypothesis (derandomized: the same examples every run) and
at the edges (the range's ends, cantools' tolerance, halfway between two raw values, negative,
-0.0)."""

from __future__ import annotations

import functools
import math
import tempfile
from pathlib import Path
from typing import Any

import cantools
import numpy as np
import pytest
from cantools.database.can import Message
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from hypothesis.configuration import set_hypothesis_home_dir

from rigbus.codec import MISSING, WRAPPING_SIGNALS, FrameError, MessageCodec
from rigbus.protocol import DBC_PATH

DATABASE = cantools.database.load_file(str(DBC_PATH), strict=True)
MESSAGES = DATABASE.messages
# derandomized (the same examples every run), and nothing written in the checkout: hypothesis's
# own files (the constants it collects from the source) go to the temporary folder, and there is
# no example database and no patch of failing examples (the explain phase writes those)
set_hypothesis_home_dir(str(Path(tempfile.gettempdir()) / "softhil-hypothesis"))
EXAMPLES = settings(
    derandomize=True,
    database=None,
    phases=[Phase.explicit, Phase.generate, Phase.shrink],
    max_examples=30,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)

# byte-aligned signals with integer and fractional offsets, signed and unsigned, an int scale
# with an int offset, a negative scale (with and without offsets: cantools adds an offset of 0,
# which makes raw 0 times a negative scale 0.0, not -0.0) and a 1-bit flag: every one a struct
# holds
ALIGNED_DBC = """VERSION ""
NS_ :
BS_:
BU_: Rig
BO_ 256 Offsets: 8 Rig
 SG_ temperature : 0|16@1- (0.01,-40) [-100|250] "degC" Rig
 SG_ level : 16|16@1+ (0.5,10.5) [10.5|2000] "mm" Rig
 SG_ trim : 32|8@1- (1,-3) [-100|100] "" Rig
 SG_ steps : 40|8@1+ (4,2) [2|1000] "" Rig
 SG_ flag : 48|1@1+ (1,0) [0|1] "" Rig
 SG_ reversed : 56|8@1- (-0.5,0) [-60|60] "" Rig
BO_ 257 Wrapping: 2 Rig
 SG_ counter : 0|8@1- (1,0) [-128|127] "" Rig
 SG_ frame_index : 8|8@1+ (1,0) [0|255] "" Rig
BO_ 258 Reversed: 2 Rig
 SG_ angle : 0|16@1- (-0.01,0) [-300|300] "deg" Rig
"""

# layouts a struct cannot hold: across bytes, big-endian, a float, no range, a range wider
# than the bits; cantools encodes them after the same checks
UNALIGNED_DBC = """VERSION ""
NS_ :
BS_:
BU_: Rig
BO_ 512 Across: 8 Rig
 SG_ level : 4|12@1+ (0.5,10.5) [10.5|2000] "mm" Rig
 SG_ gain : 36|20@1+ (0.001,0) [0|1000] "" Rig
BO_ 513 Motorola: 2 Rig
 SG_ speed : 7|16@0- (0.1,0) [-3000|3000] "" Rig
BO_ 514 Floating: 4 Rig
 SG_ ratio : 0|32@1- (1,0) [-1000|1000] "" Rig
BO_ 515 Unbounded: 1 Rig
 SG_ raw : 0|8@1+ (1,0) [0|0] "" Rig
BO_ 516 Clipped: 1 Rig
 SG_ wide : 0|8@1+ (1,0) [0|1000] "" Rig
SIG_VALTYPE_ 514 ratio : 1;
"""


def _database(text: str) -> list[Message]:
    return cantools.database.load_string(text, strict=True).messages


ALIGNED = _database(ALIGNED_DBC)
UNALIGNED = _database(UNALIGNED_DBC)
# a message of each kind (the DBC gives every message of a kind the same layout, and the edge
# test below takes every message)
KINDS = list({m.name.rstrip("0123456789"): m for m in reversed(MESSAGES)}.values()) + ALIGNED


@functools.cache
def codec_of(message: Message, compiled: bool = True) -> MessageCodec:
    return MessageCodec(message, compiled)


def same(have: dict[str, Any], want: dict[str, Any]) -> bool:
    """The same values by name, in the same order, bit for bit: types, -0.0 and all."""
    return [(k, type(v), repr(v)) for k, v in have.items()] == [
        (k, type(v), repr(v)) for k, v in want.items()
    ]


def cantools_outcome(message: Message, values: dict[str, Any]) -> bytes | str:
    """cantools' strict encoding of `values`, or its error in our words (frame, id, its text)."""
    try:
        return message.encode(values, strict=True)
    except cantools.database.EncodeError as exc:
        return f"{message.name} (0x{message.frame_id:03X}): {exc}"


def codec_outcome(codec: MessageCodec, values: dict[str, Any]) -> bytes | str:
    try:
        return codec.encode(codec.values_of(values))
    except FrameError as exc:
        text = str(exc)
        assert "\n" not in text
        return text


@functools.cache
def in_range(signal: Any) -> st.SearchStrategy[Any]:
    """A value cantools accepts for `signal`: a float within its range, an int for an integer
    signal."""
    low, high = float(signal.minimum), float(signal.maximum)
    if signal.name in WRAPPING_SIGNALS:  # an int is taken modulo the range: one inside it
        low = max(low, 0.0)
    if signal.scale == 1 and signal.offset == 0:
        return st.integers(math.ceil(low), math.floor(high))
    return st.floats(low, high, allow_nan=False, allow_infinity=False)


def test_every_message_of_the_dbc_has_a_struct() -> None:
    """The fast path serves every message of softhil's DBC (none is left to cantools)."""
    for message in MESSAGES:
        assert MessageCodec(message).compiled, message.name
    assert all(MessageCodec(message).compiled for message in ALIGNED)
    assert not any(MessageCodec(message).compiled for message in UNALIGNED)


@pytest.mark.parametrize("message", KINDS, ids=lambda m: m.name)
@EXAMPLES
@given(data=st.data())
def test_values_in_range_encode_as_cantools_encodes(message: Message, data: st.DataObject) -> None:
    values = {s.name: data.draw(in_range(s)) for s in message.signals}
    codec = codec_of(message)
    expected = message.encode(values, strict=True)
    assert codec.encode(codec.values_of(values)) == expected
    # and the payload decodes to cantools' values, types included
    want = message.decode(expected, decode_choices=False)
    have = codec.as_mapping(codec.decode(bytearray(expected)))
    assert same(have, want)


@pytest.mark.parametrize("message", KINDS + UNALIGNED, ids=lambda m: m.name)
@EXAMPLES
@given(data=st.data())
def test_every_payload_decodes_as_cantools_decodes(message: Message, data: st.DataObject) -> None:
    payload = data.draw(st.binary(min_size=message.length, max_size=message.length))
    codec = codec_of(message)
    want = message.decode(payload, decode_choices=False)
    have = codec.as_mapping(codec.decode(payload))
    assert same(have, want)


def edges(signal: Any) -> list[float]:
    """The values where an encoder goes wrong: the range's ends, a millionth of the scale (cantools'
    tolerance) inside and outside them, twice that, halfway between two raw values and an ulp
    either side (round half to even), exact multiples of the scale, negatives, zeros."""
    low, high, scale, offset = (
        float(signal.minimum),
        float(signal.maximum),
        signal.scale,
        signal.offset,
    )
    values = [low, high, 0.0, -0.0, -low, -high, (low + high) / 2]
    for end in (low, high):
        for factor in (0.5e-6, 0.99e-6, 1e-6, 1.01e-6, 2e-6, 0.5, 1.0):
            values += [end - abs(scale) * factor, end + abs(scale) * factor]
    for k in (-3, -2, -1, 0, 1, 2, 3, 1234, -1234, 6150, 22800):
        half = (k + 0.5) * scale + offset
        values += [k * scale + offset, half, math.nextafter(half, math.inf)]
        values += [math.nextafter(half, -math.inf)]
    if signal.name in WRAPPING_SIGNALS:  # an int would be taken modulo the range: a float is not
        return [float(v) for v in values]
    return values


@pytest.mark.parametrize("message", MESSAGES + ALIGNED, ids=lambda m: m.name)
def test_edge_values_encode_or_fail_as_cantools_does(message: Message) -> None:
    """Each signal at each edge value (the others in range): the same bytes, or the same
    one-line refusal naming the frame, its CAN id and the signal, as cantools'."""
    codec = MessageCodec(message)
    base = {s.name: max(float(s.minimum), min(float(s.maximum), 0.0)) for s in message.signals}
    refused = 0
    for signal in message.signals:
        for value in edges(signal):
            values = {**base, signal.name: value}
            expected = cantools_outcome(message, values)
            assert codec_outcome(codec, values) == expected, (signal.name, value)
            if isinstance(expected, str):
                assert f'signal "{signal.name}"' in expected
                refused += 1
    assert refused > 0


BEYOND = st.floats(1e-4, 1e6)  # how far out of its range a value is, in spans of the range


@pytest.mark.parametrize("message", KINDS, ids=lambda m: m.name)
@EXAMPLES
@given(data=st.data())
def test_out_of_range_values_are_refused_with_cantools_text(
    message: Message, data: st.DataObject
) -> None:
    """A value beyond its range by more than cantools' tolerance: FrameError naming the frame,
    its CAN id and the signal, in one line, with cantools' words (a value the signal names in
    its value table is not out of range, as in cantools)."""
    signal = message.signals[data.draw(st.integers(0, len(message.signals) - 1))]
    values = {s.name: data.draw(in_range(s)) for s in message.signals}
    low, high = float(signal.minimum), float(signal.maximum)
    beyond = data.draw(BEYOND) * max(high - low, abs(signal.scale))
    values[signal.name] = high + beyond if data.draw(st.booleans()) else low - beyond
    expected = cantools_outcome(message, values)
    assert codec_outcome(codec_of(message), values) == expected
    if isinstance(expected, str):
        assert expected.startswith(f"{message.name} (0x{message.frame_id:03X}): Expected signal ")


SPECIALS: list[Any] = [math.nan, math.inf, -math.inf, True, False, -0.0, 256, 257, -1, -257]
SPECIALS += [10**20, -(10**20), 2**63, "7", None, 1.5, np.float64(0.25), np.int64(3), MISSING]


@functools.cache
def any_value(signal: Any) -> st.SearchStrategy[Any]:
    """A value of any kind: in range, at the edges, out of range, ints, numpy scalars, specials
    (NaN, infinities, bools, wrapping counters, not numbers, missing)."""
    low, high = float(signal.minimum), float(signal.maximum)
    return st.one_of(
        in_range(signal),
        st.sampled_from(edges(signal)),
        st.floats(low - (high - low), high + (high - low)),
        st.integers(int(low) - 300, int(high) + 300),
        st.sampled_from(SPECIALS),
    )


@pytest.mark.parametrize("message", KINDS, ids=lambda m: m.name)
@EXAMPLES
@given(data=st.data())
def test_the_struct_and_cantools_paths_agree_on_any_value(
    message: Message, data: st.DataObject
) -> None:
    """The same checks then the struct, or the same checks then cantools: the same bytes or
    the same error line, for values of every kind."""
    values = [data.draw(any_value(s)) for s in message.signals]
    names = [s.name for s in message.signals]
    outcomes = []
    for codec in (codec_of(message), codec_of(message, compiled=False)):
        by_name = dict(zip(names, values, strict=True))
        try:
            outcomes.append(codec.encode(codec.values_of(by_name)))
        except FrameError as exc:
            outcomes.append(str(exc))
    assert outcomes[0] == outcomes[1]


@pytest.mark.parametrize(
    ("value", "text"),
    [
        (MISSING, "no value for signal piston_position"),
        ("7", "piston_position is not a number: '7'"),
        (None, "piston_position is not a number: None"),
        (math.nan, "piston_position is nan"),
        (-math.inf, "piston_position is -inf"),
    ],
)
def test_values_that_are_not_finite_numbers_are_refused_naming_the_signal(
    value: Any, text: str
) -> None:
    message = DATABASE.get_message_by_name("DriveCommand2")
    for codec in (MessageCodec(message), MessageCodec(message, compiled=False)):
        values = {"piston_setpoint": 0.05, "enable": 1, "counter": 3}
        values["piston_setpoint"] = value
        with pytest.raises(FrameError) as info:
            codec.encode(codec.values_of(values))
        assert (
            str(info.value)
            == f"DriveCommand2 (0x202): {text.replace('piston_position', 'piston_setpoint')}"
        )


@pytest.mark.parametrize(
    ("counter", "raw"), [(256, 0), (257, 1), (-1, 255), (300, 44), (255, 255), (True, 1)]
)
def test_sequence_numbers_given_as_ints_wrap_and_bools_are_ints(counter: Any, raw: int) -> None:
    message = DATABASE.get_message_by_name("DriveCommand2")
    codec = MessageCodec(message)
    data = codec.encode(
        codec.values_of({"piston_setpoint": 0.0, "enable": True, "counter": counter})
    )
    assert data == bytes([0, 0, 1, raw])
    # a float counter is a value like any other: checked against the range
    with pytest.raises(
        FrameError, match=r"value smaller than or equal to 255 .* but got 256\.0\.$"
    ):
        codec.encode(codec.values_of({"piston_setpoint": 0.0, "enable": 1, "counter": 256.0}))


def test_a_signed_sequence_number_wraps_into_its_range_and_a_flag_keeps_its_bit() -> None:
    """A wrapping signal whose range is signed takes an int modulo its range (-1 is 127), on
    both paths; a 1-bit flag leaves its byte's other bits 0, and ignores them when decoding."""
    wrapping, offsets = ALIGNED[1], ALIGNED[0]
    for codec in (MessageCodec(wrapping), MessageCodec(wrapping, compiled=False)):
        for frame_index in (300, 44):  # the other value wrapped or not
            values = {"counter": -1, "frame_index": frame_index}
            assert codec.encode(codec.values_of(values)) == bytes([127, 44])
    codec = MessageCodec(offsets)
    payload = bytearray(8)
    payload[6] = 0xFF
    assert codec.as_mapping(codec.decode(payload))["flag"] == 1
    values = {s.name: float(s.minimum) for s in offsets.signals}
    assert codec.encode(codec.values_of({**values, "flag": True}))[6] == 1
