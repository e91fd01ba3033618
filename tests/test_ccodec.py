"""The DBC codec's C path (`rigbus.ccodec`) against the codec's Python path it speeds up
(`rigbus.codec`, itself checked against cantools in tests/test_codec.py): the same bytes, the
same frames (values, types, field order) and the same errors, value by value, for every message
of our DBC and for a DBC with offsets; the plain case taken in C, everything else handed to
Python."""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path
from typing import Any

import can
import cantools
import numpy as np
import pytest

from rigbus import ccodec
from rigbus.codec import MISSING, FrameError, MessageCodec
from rigbus.protocol import (
    _REGISTRY,
    DriveStatus,
    FrameType,
    Protocol,
    _builder,
    _Entry,
    frame_key,
)
from tests import test_codec, test_protocol

OFFSETS = cantools.database.load_string(test_codec.ALIGNED_DBC, strict=True)

module = ccodec.load()
needs_c = pytest.mark.skipif(module is None, reason=f"no C codec here: {ccodec.failure()}")


def test_the_c_codec_builds_where_a_compiler_and_headers_are() -> None:
    """With gcc and Python.h (as on every machine the README sets up) the fast path is in use
    for every message of the DBC: losing it would only show as a slower loop."""
    if shutil.which("gcc") is None or ccodec.failure() == f"{ccodec.ENV}=python":
        pytest.skip("no gcc, or the C codec switched off")
    assert module is not None, ccodec.failure()
    protocol = Protocol()
    for entry in protocol._by_name.values():
        assert ccodec.encoder(entry.codec) is not None, entry.message.name
        if entry.type is not None:
            ftype = entry.type
            decoder = ccodec.decoder(
                entry.codec, ftype.cls, ftype.kinds, ftype.index_field, entry.index
            )
            assert decoder is not None, entry.message.name


def _values(rng: np.random.Generator, codec: MessageCodec, specials: list[Any]) -> tuple:
    """One frame's values: floats in range, at the range's ends and at cantools' tolerance,
    halfway between two raw values (round half to even) and an ulp either side, out of range,
    ints, numpy scalars and the specials."""
    values: list[Any] = []
    for s in codec.fields:
        signal = codec.message.get_signal_by_name(s.name)
        lo, hi, scale, offset = float(signal.minimum), float(signal.maximum), s.scale, s.offset
        pick = rng.random()
        if pick < 0.3:
            v: Any = float(rng.uniform(lo, hi))
        elif pick < 0.45:  # a raw value and a half: rounds to even, as Python's round
            raw = math.floor((float(rng.uniform(lo, hi)) - offset) / scale)
            v = (raw + 0.5) * scale + offset
            v = float(rng.choice([v, math.nextafter(v, math.inf), math.nextafter(v, -math.inf)]))
        elif pick < 0.55:
            v = float(rng.choice([lo, hi]))
        elif pick < 0.6:  # cantools' tolerance at the ends, inside or outside
            margin = abs(scale) * float(rng.choice([0.5e-6, 2e-6]))
            v = float(rng.choice([lo - margin, hi + margin]))
        elif pick < 0.65:
            v = float(rng.uniform(lo, hi) + (hi - lo) * rng.choice([-0.6, 0.6]))
        elif pick < 0.78:
            v = int(rng.integers(int(lo) - 2, int(hi) + 3))
        elif pick < 0.83:
            v = np.float64(rng.uniform(lo, hi))
        elif pick < 0.86:
            v = np.int64(rng.integers(int(lo), int(hi) + 1))
        else:
            v = specials[int(rng.integers(len(specials)))]
        values.append(v)
    return tuple(values)


SPECIALS = [math.nan, math.inf, -math.inf, True, False, -0.0, 0.0, 256, 257, -1, -257]
SPECIALS += [10**20, -(10**20), 2**63, "7", None, 1.5, MISSING]


def _outcome(encode: Any, values: tuple) -> Any:
    try:
        return bytes(encode(values))
    except FrameError as exc:
        return f"{type(exc).__name__}: {exc}"


def _codecs() -> list[MessageCodec]:
    return [MessageCodec(m) for m in Protocol().database.messages + OFFSETS.messages]


@needs_c
def test_c_encoding_equals_the_python_codec_value_by_value() -> None:
    """`pack` in C gives the codec's bytes wherever it gives any, for values of every kind;
    most plain frames are encoded in C (not all handed back to Python), and the Python path
    refuses many."""
    assert module is not None
    rng = np.random.default_rng(21)
    compared = in_c = refused = 0
    for codec in _codecs():
        encoder = ccodec.encoder(codec)
        assert encoder is not None, codec.message.name
        for _ in range(400):
            values = _values(rng, codec, SPECIALS)
            expected = _outcome(codec.encode, values)
            direct = module.pack(encoder, values)
            if direct is not None:
                assert direct == expected, (codec.message.name, values)
                in_c += 1
            compared += 1
            refused += isinstance(expected, str)
    assert in_c > 0.2 * compared and 0.1 * compared < refused < 0.9 * compared, (
        in_c,
        refused,
        compared,
    )


@needs_c
def test_plain_floats_and_counters_are_encoded_in_c() -> None:
    """The loop's common frame, floats in range and its counter, takes the C path (so the
    speed-up is real) and gives the Python bytes; a counter past its modulus (as a sender's
    running count is, from the 256th frame on) is wrapped in C too, as Python's % wraps it, and
    the bytes are those of the checked path."""
    assert module is not None
    codec = Protocol()._by_name["DriveStatus2"].codec
    encoder = ccodec.encoder(codec)
    values = codec.values_of(
        {"piston_position": 0.0311, "p_a": 2345.6, "p_b": -0.0, "fault": 3, "counter": 255}
    )
    data = module.pack(encoder, values)
    assert data is not None and data == codec.encode(values)
    wrapped = codec.values_of(
        {"piston_position": 0.0311, "p_a": 2345.6, "p_b": -0.0, "fault": 3, "counter": 300}
    )
    assert module.pack(encoder, wrapped) == codec.encode(wrapped) == codec._encode_checked(wrapped)
    assert codec.encode(wrapped)[7] == 300 % 256
    for counter in (256, 511, -1, -257, 2**40 + 7):
        values = codec.values_of({**codec.as_mapping(wrapped), "counter": counter})
        assert module.pack(encoder, values) == codec._encode_checked(values)
        assert module.pack(encoder, values)[7] == counter % 256
    # a bool is not a sequence number's int: it is never taken modulo (True is 1 either way)
    values = codec.values_of({**codec.as_mapping(wrapped), "counter": True})
    assert module.pack(encoder, values) == codec._encode_checked(values)


@needs_c
def test_a_raw_value_its_field_does_not_hold_is_never_packed() -> None:
    """The C encoder packs a raw value only within its field's bits (the codec's quick range
    keeps to them; a plan that did not would be refused value by value, not wrapped)."""
    assert module is not None
    # an 8-bit field of scale 1 whose quick range claims -1000..1000
    for signed, bounds in ((True, (-128, 127)), (False, (0, 255))):
        low, high = ccodec._raw_range(8, signed)
        assert (low, high) == bounds
        encoder = module.compile_encoder(1, ((0, 0xFF, True, 1, True, 0, -1e3, 1e3, low, high, 0),))
        assert module.pack(encoder, (high,)) == bytes([high & 0xFF])
        assert module.pack(encoder, (low,)) == bytes([low & 0xFF])
        assert module.pack(encoder, (high + 1,)) is None, signed
        assert module.pack(encoder, (low - 1,)) is None, signed


def _payloads(rng: np.random.Generator, length: int) -> list[bytes]:
    edges = [bytes(length), bytes([0xFF] * length), bytes([0x80] * length), bytes([0x7F] * length)]
    return edges + [bytes(rng.integers(0, 256, length).tolist()) for _ in range(150)]


def _field_types(frame: Any) -> list[type]:
    return [type(getattr(frame, f.name)) for f in dataclasses.fields(frame)]


@needs_c
def test_c_decoding_builds_the_frames_the_python_codec_builds() -> None:
    """Every typed message: the same frame, field types and field order as the Python builder,
    a slotted frame, still frozen; a payload whose index field disagrees with the CAN id is left
    to the Python path, which refuses it."""
    assert module is not None
    protocol = Protocol()
    rng = np.random.default_rng(5)
    decoded = refused = 0
    for entry in protocol._by_name.values():
        ftype = entry.type
        if ftype is None:
            continue
        python = _builder(entry)
        fast = ccodec.decoder(entry.codec, ftype.cls, ftype.kinds, ftype.index_field, entry.index)
        assert fast is not None, entry.message.name
        for data in _payloads(rng, entry.codec.length):
            try:
                want: Any = python(data)
            except FrameError:
                assert module.unpack(fast, bytearray(data)) is None
                refused += 1
                continue
            have = module.unpack(fast, bytearray(data))
            assert have == want and type(have) is type(want), (entry.message.name, data.hex())
            assert _field_types(have) == _field_types(want)
            assert frame_key(have) == frame_key(want) and not hasattr(have, "__dict__")
            with pytest.raises(dataclasses.FrozenInstanceError):
                setattr(have, dataclasses.fields(have)[0].name, 1)
            decoded += 1
    assert decoded > 1000 and refused > 0


@dataclasses.dataclass(frozen=True, slots=True)
class Offsets:
    temperature: float
    level: int
    trim: bool
    steps: float
    flag: bool
    reversed: int


@needs_c
def test_c_decoding_follows_python_types_through_scales_and_offsets() -> None:
    """Int scale and offset (exact ints), float scale with an int or a float offset, a negative
    scale, into float, int and bool fields (int(v) truncates a float towards zero): the frames
    the Python builder makes."""
    assert module is not None
    message = OFFSETS.get_message_by_name("Offsets")
    kinds = {"temperature": "float", "level": "int", "trim": "bool", "steps": "float"}
    ftype = FrameType("Offsets", Offsets, None, {**kinds, "flag": "bool", "reversed": "int"})
    codec = MessageCodec(message)
    entry = _Entry("Offsets", None, message, ftype, codec)
    fast = ccodec.decoder(codec, Offsets, ftype.kinds, None, None)
    assert fast is not None
    python = _builder(entry)
    rng = np.random.default_rng(9)
    for data in _payloads(rng, 8):
        have, want = module.unpack(fast, data), python(data)
        assert have == want and _field_types(have) == _field_types(want), data.hex()


def test_classes_with_more_than_their_fields_keep_the_python_decoder() -> None:
    """A frame class whose `__init__` does more than fill its fields' slots (a __post_init__,
    an InitVar), or whose instances have a dict, is built by calling it, never by the C
    decoder."""

    @dataclasses.dataclass(frozen=True, slots=True)
    class Checked(Offsets):
        def __post_init__(self) -> None:
            if self.level < 0:
                raise ValueError("negative level")

    @dataclasses.dataclass(frozen=True)
    class Unslotted:
        temperature: float
        level: int
        trim: bool
        steps: float
        flag: bool
        reversed: int

    @dataclasses.dataclass(frozen=True, slots=True)
    class WithInitVar:
        temperature: float
        level: int
        trim: bool
        steps: float
        flag: bool
        reversed: int
        scale: dataclasses.InitVar[float] = 1.0

    codec = MessageCodec(OFFSETS.get_message_by_name("Offsets"))
    kinds = {f.name: "float" for f in dataclasses.fields(Offsets)}
    for cls in (Checked, Unslotted, WithInitVar):
        assert ccodec.decoder(codec, cls, kinds, None, None) is None, cls.__name__
    if module is not None:
        assert ccodec.decoder(codec, Offsets, kinds, None, None) is not None


def test_the_python_codec_alone_gives_the_same_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    """SOFTHIL_CODEC=python: no C module is built or loaded, and the frames and bytes of every
    kind are the same."""
    with_c = Protocol()
    monkeypatch.setattr(ccodec._part, "value", None)
    monkeypatch.setattr(ccodec._part, "failure", None)
    monkeypatch.setenv(ccodec.ENV, "python")
    assert ccodec.load() is None and ccodec.failure() == "SOFTHIL_CODEC=python"
    python = Protocol()
    codec = python._by_name["DriveStatus4"].codec
    assert ccodec.encoder(codec) is None
    assert ccodec.decoder(codec, DriveStatus, _REGISTRY["DriveStatus"].kinds, "node", 4) is None
    for frame, _, _ in test_protocol.GOLDEN:
        for _ in range(2):  # the first encoding and decoding, then the remembered ones
            message = python.encode(frame)
            assert message.equals(with_c.encode(frame), check_channel=True)
            assert python.decode(message) == with_c.decode(message)
    frame = DriveStatus(4, 0.0123, 1230.0, -4560.0, 0x12, 0xC7)
    assert python.decode(python.encode(frame)) == DriveStatus(
        4, 6150 * 2e-06, 1230.0, -4560.0, 0x12, 0xC7
    )


def test_a_misspelt_codec_setting_is_one_line_in_hil_and_the_controller(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """SOFTHIL_CODEC=pyhton is refused (it silently meant "c"), by `hil` before any command
    and by the controller program before it opens the bus; "C" and "Python" are accepted."""
    from controllers.__main__ import main as controller_main
    from hil.cli import main as hil_main

    for value, meant in (("", "c"), ("C", "c"), (" Python ", "python")):
        monkeypatch.setenv(ccodec.ENV, value)
        assert ccodec.setting() == meant
    monkeypatch.setenv(ccodec.ENV, "pyhton")
    monkeypatch.setattr(ccodec._part, "value", None)
    monkeypatch.setattr(ccodec._part, "failure", None)
    with pytest.raises(ValueError, match="^SOFTHIL_CODEC='pyhton': must be c .* or python$"):
        ccodec.load()
    assert hil_main(["scenarios"]) == 1
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("hil: error: SOFTHIL_CODEC='pyhton': must be c")
    assert err.count("\n") == 1
    (tmp_path / "controller.json").write_text("{}")
    assert controller_main(["--config", str(tmp_path / "controller.json")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("controller: error: SOFTHIL_CODEC='pyhton'") and err.count("\n") == 1


def test_a_damaged_cache_entry_is_built_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A cached module that does not load (cut short, overwritten) is compiled again, not
    silently replaced by the slow path."""
    if shutil.which("gcc") is None:
        pytest.skip("no gcc")
    monkeypatch.setenv("SOFTHIL_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv(ccodec.ENV, raising=False)
    monkeypatch.setattr(ccodec._part, "value", None)
    monkeypatch.setattr(ccodec._part, "failure", None)
    target = ccodec._build()
    target.write_bytes(b"not a shared library")
    rebuilt = ccodec.load()
    assert rebuilt is not None, ccodec.failure()
    assert target.read_bytes()[:4] == b"\x7fELF"
    assert rebuilt.pack is not None


FIELDS = [name for name in can.Message.__slots__ if name != "__weakref__"]


@needs_c
def test_messages_made_in_c_are_unchecked_message_s() -> None:
    """new_message and copy_message fill python-can's slots as `unchecked_message` and the direct
    bus's `_copy` set them: every field, its type, and a copy of the data of its own."""
    from hil.bus.direct import _copy
    from rigbus.canbus import c_messages, unchecked_message

    made = c_messages()
    assert made is not None
    values = (2.5, 0x1ABCDE, True, False, False, "ch", 3, bytearray(b"\x01\x02\x03"), False,
              True, False, False)  # fmt: skip
    ours, reference = made.new_message(*values), unchecked_message(*values)
    originals = [
        reference,
        can.Message(arbitration_id=0x7, is_remote_frame=True, dlc=3, is_extended_id=False),
        can.Message(arbitration_id=0x9, data=bytes(12), is_fd=True, bitrate_switch=True),
        can.Message(arbitration_id=0x1, is_error_frame=True, channel=3, is_rx=False),
    ]
    pairs = [(ours, reference)]
    pairs += [(made.copy_message(m, "out"), _copy(m, "out")) for m in originals]
    for (c, python), original in zip(pairs, [reference, *originals], strict=False):
        assert type(c) is can.Message
        for name in FIELDS:
            assert getattr(c, name) == getattr(python, name), name
            assert type(getattr(c, name)) is type(getattr(python, name)), name
        if c is not ours:
            assert c.data is not original.data and c.channel == "out"
    with pytest.raises(TypeError):
        made.new_message(1.0, 2)


@needs_c
def test_a_message_c_does_not_copy_is_left_to_python() -> None:
    """Another class (a subclass too) or a field never set: None, and Python copies it (or
    fails as it always did); a class whose fields are not plain slots is not bound."""
    from rigbus.canbus import c_messages

    made = c_messages()
    assert made is not None

    class Tagged(can.Message):
        __slots__ = ("tag",)

    assert made.copy_message(Tagged(arbitration_id=1, data=b"\x01"), "x") is None
    unset = can.Message.__new__(can.Message)
    assert made.copy_message(unset, "x") is None
    assert made.copy_message(object(), "x") is None

    class Plain:
        timestamp = 0.0

    assert made.bind_message(Plain) is False
    assert made.bind_message(can.Message) is True
