"""Tests for rigbus.protocol and the DBC file: ids, ranges, round trips, errors, bus load.

Round trips run over every node (1..8) and every marker (0..15) with seeded random values; the
decoded value must lie within half a scaling step of the encoded one (cantools rounds). The
interoperability test writes a candump `.log` line with python-can and decodes it with cantools.
"""

from __future__ import annotations

import dataclasses
import io
import math
from collections.abc import Callable
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
from cantools.database.can import Database

from hil.fmu.build import model_folder
from hil.fmu.spec import load_spec
from rigbus.codec import MessageCodec
from rigbus.protocol import (
    DBC_PATH,
    EMCY_COMMAND_TIMEOUT,
    EMCY_FMU_FAULT,
    EMCY_OVER_PRESSURE,
    NMT_OPERATIONAL,
    CameraFrame,
    CameraMarker,
    CameraMarker3D,
    ControllerState,
    DriveCommand,
    DriveStatus,
    Emcy,
    Frame,
    FrameError,
    GenericFrame,
    Heartbeat,
    Protocol,
    SpatialTaskState,
    Sync,
    TaskState,
    bus_load,
    frame_bits,
    frame_key,
    frame_signals,
)

NODES = range(1, 17)  # drive nodes: the spatial arm's 4 segments take 8, 8 segments 16
MARKERS = range(16)
# scaling steps of the DBC signals
PISTON_RES = 2e-6  # [m]
PRESSURE_RES = 10.0  # [Pa]
MARKER_RES = 2e-5  # [m]
KAPPA_RES = 1e-3  # [1/m]
EXPOSURE_RES = 1e-5  # [s]
# the physics the ranges must cover
PISTON_STROKE = 0.1  # [m] the 100 mm drive cylinder of the spatial arm
P_VACUUM = -101325.0  # [Pa gauge] full vacuum
P_MAX = 300e3  # [Pa gauge]
KAPPA_REACH = 1.6 / 0.06  # [1/m] theta_max / L = 26.67
MARKER_REACH = 0.5  # [m]


@pytest.fixture(scope="module")
def protocol() -> Protocol:
    return Protocol()


def close(decoded: float, encoded: float, resolution: float) -> bool:
    """Within half a scaling step (plus float noise): what rounding to the nearest step gives."""
    return abs(decoded - encoded) <= 0.5 * resolution * (1.0 + 1e-9)


def round_trip(protocol: Protocol, frame: Frame) -> Frame:
    message = protocol.encode(frame)
    assert not message.is_extended_id
    assert len(message.data) == protocol.message(message.arbitration_id).length
    return protocol.decode(message)


def test_sync_round_trip_for_every_counter(protocol: Protocol) -> None:
    for counter in range(256):
        assert round_trip(protocol, Sync(counter)) == Sync(counter)


@pytest.mark.parametrize("node", NODES)
def test_drive_status_round_trip(protocol: Protocol, node: int) -> None:
    rng = np.random.default_rng(node)
    cases = [(0.0, P_VACUUM, P_MAX), (PISTON_STROKE, P_MAX, P_VACUUM)]
    cases += [
        (rng.uniform(0, PISTON_STROKE), rng.uniform(P_VACUUM, P_MAX), rng.uniform(P_VACUUM, P_MAX))
        for _ in range(20)
    ]
    for i, (x, p_a, p_b) in enumerate(cases):
        frame = DriveStatus(node, float(x), float(p_a), float(p_b), fault=i % 256, counter=7 * i)
        back = round_trip(protocol, frame)
        assert isinstance(back, DriveStatus)
        assert (back.node, back.fault, back.counter) == (node, i, 7 * i)
        assert isinstance(back.fault, int) and isinstance(back.counter, int)
        assert close(back.piston_position, x, PISTON_RES)
        assert close(back.p_a, p_a, PRESSURE_RES)
        assert close(back.p_b, p_b, PRESSURE_RES)


@pytest.mark.parametrize("node", NODES)
def test_drive_command_round_trip(protocol: Protocol, node: int) -> None:
    rng = np.random.default_rng(100 + node)
    setpoints = [0.0, PISTON_STROKE, *rng.uniform(0.0, PISTON_STROKE, 20)]
    for i, x in enumerate(setpoints):
        frame = DriveCommand(node, float(x), enable=bool(i % 2), counter=i)
        back = round_trip(protocol, frame)
        assert isinstance(back, DriveCommand)
        assert (back.node, back.enable, back.counter) == (node, bool(i % 2), i)
        assert isinstance(back.enable, bool)
        assert close(back.piston_setpoint, x, PISTON_RES)


@pytest.mark.parametrize("node", NODES)
def test_controller_state_round_trip(protocol: Protocol, node: int) -> None:
    rng = np.random.default_rng(200 + node)
    pairs = [(-KAPPA_REACH, KAPPA_REACH), (KAPPA_REACH, -KAPPA_REACH), (0.0, 0.0)]
    pairs += [tuple(rng.uniform(-KAPPA_REACH, KAPPA_REACH, 2)) for _ in range(20)]
    for i, (ref, est) in enumerate(pairs):
        back = round_trip(protocol, ControllerState(node, float(ref), float(est), counter=i))
        assert isinstance(back, ControllerState)
        assert (back.node, back.counter) == (node, i)
        assert close(back.kappa_ref, ref, KAPPA_RES)
        assert close(back.kappa_est, est, KAPPA_RES)


@pytest.mark.parametrize("node", NODES)
def test_emcy_round_trip(protocol: Protocol, node: int) -> None:
    rng = np.random.default_rng(300 + node)
    codes = (EMCY_OVER_PRESSURE, EMCY_COMMAND_TIMEOUT, EMCY_FMU_FAULT, 0, 0xFFFF)
    for i, code in enumerate(codes):
        pressure = float(rng.uniform(P_VACUUM, P_MAX))
        back = round_trip(
            protocol, Emcy(node, code, error_register=0x81, pressure=pressure, counter=i)
        )
        assert isinstance(back, Emcy)
        assert (back.node, back.error_code, back.error_register, back.counter) == (
            node,
            code,
            0x81,
            i,
        )
        assert close(back.pressure, pressure, PRESSURE_RES)


@pytest.mark.parametrize("node", NODES)
def test_heartbeat_round_trip(protocol: Protocol, node: int) -> None:
    for state in (0, 4, NMT_OPERATIONAL, 127, 255):
        assert round_trip(protocol, Heartbeat(node, state)) == Heartbeat(node, state)


@pytest.mark.parametrize("marker", MARKERS)
def test_camera_marker_round_trip(protocol: Protocol, marker: int) -> None:
    rng = np.random.default_rng(400 + marker)
    cases = [(-MARKER_REACH, MARKER_REACH, 0.0), (MARKER_REACH, -MARKER_REACH, 0.5)]
    cases += [
        (*rng.uniform(-MARKER_REACH, MARKER_REACH, 2), rng.uniform(0.0, 0.5)) for _ in range(20)
    ]
    for i, (x, y, exposure) in enumerate(cases):
        frame = CameraMarker(marker, float(x), float(y), frame_index=i, exposure_offset=exposure)
        back = round_trip(protocol, frame)
        assert isinstance(back, CameraMarker)
        assert (back.marker_id, back.frame_index) == (marker, i)
        assert close(back.x, x, MARKER_RES)
        assert close(back.y, y, MARKER_RES)
        assert close(back.exposure_offset, exposure, EXPOSURE_RES)


def test_exact_bytes_of_a_drive_command(protocol: Protocol) -> None:
    # 0.1 m / 2e-6 = 50000 = 0xC350 little-endian at bit 0, enable at bit 16, counter at byte 3
    message = protocol.encode(DriveCommand(2, 0.1, enable=True, counter=3))
    assert message.arbitration_id == 0x202
    assert bytes(message.data) == bytes([0x50, 0xC3, 0x01, 0x03])


IDS: list[tuple[Frame, int]] = [
    (Sync(0), 0x080),
    *[(DriveStatus(n, 0.0, 0.0, 0.0, 0, 0), 0x180 + n) for n in NODES],
    *[(DriveCommand(n, 0.0, False, 0), 0x200 + n) for n in NODES],
    *[(CameraMarker(m, 0.0, 0.0, 0, 0.0), 0x280 + m) for m in MARKERS],
    *[(ControllerState(n, 0.0, 0.0, 0), 0x380 + n) for n in NODES],
    *[(Emcy(n, 0, 0, 0.0, 0), 0x080 + n) for n in NODES],
    *[(Heartbeat(n, NMT_OPERATIONAL), 0x700 + n) for n in NODES],
]


def test_ids_follow_canopen_ranges(protocol: Protocol) -> None:
    for frame, expected in IDS:
        assert protocol.frame_id(frame) == expected, frame
        assert protocol.encode(frame).arbitration_id == expected, frame
    ids = [expected for _, expected in IDS]
    assert len(set(ids)) == len(ids) == 1 + 5 * 16 + 16


def test_dbc_names_and_ids_agree(protocol: Protocol) -> None:
    """Every message's id is its kind's CANopen-range base plus its index."""
    bases = {
        "DriveStatus": 0x180,
        "DriveCommand": 0x200,
        "CameraMarker": 0x280,
        "CameraMarker3D": 0x290,
        "ControllerState": 0x380,
        "EMCY": 0x080,
        "Heartbeat": 0x700,
        "ValveCommand": 0x210,
        "ValveStatus": 0x190,
    }
    singles = {
        "SYNC": 0x080,
        "CameraFrame": 0x27F,
        "CanisterStatus": 0x1A0,
        "TaskState": 0x3F0,
        "FishState": 0x3F1,
        "SpatialTaskState": 0x3F2,
    }
    database = protocol.database
    assert len(database.messages) == 5 * 16 + 2 * 16 + 2 * 4 + len(singles)
    ids = [m.frame_id for m in database.messages]
    assert len(ids) == len(set(ids))
    for message in database.messages:
        assert not message.is_extended_frame
        if message.name in singles:
            assert message.frame_id == singles[message.name]
            continue
        prefix = message.name.rstrip("0123456789")
        index = int(message.name[len(prefix) :])
        assert message.frame_id == bases[prefix] + index, message.name


@pytest.mark.parametrize(
    ("prefix", "signal", "low", "high"),
    [
        ("DriveStatus", "piston_position", 0.0, PISTON_STROKE),
        ("DriveStatus", "p_a", P_VACUUM, P_MAX),
        ("DriveStatus", "p_b", P_VACUUM, P_MAX),
        ("DriveCommand", "piston_setpoint", 0.0, PISTON_STROKE),
        ("EMCY", "pressure", P_VACUUM, P_MAX),
        ("ControllerState", "kappa_ref", -KAPPA_REACH, KAPPA_REACH),
        ("ControllerState", "kappa_est", -KAPPA_REACH, KAPPA_REACH),
        ("CameraMarker", "x", -MARKER_REACH, MARKER_REACH),
        ("CameraMarker", "y", -MARKER_REACH, MARKER_REACH),
    ],
)
def test_signal_ranges_cover_the_physics(
    protocol: Protocol, prefix: str, signal: str, low: float, high: float
) -> None:
    first = 0 if prefix == "CameraMarker" else 1
    for index in range(first, first + (16 if prefix == "CameraMarker" else 8)):
        spec = protocol.database.get_message_by_name(f"{prefix}{index}").get_signal_by_name(signal)
        assert spec.minimum is not None and spec.maximum is not None
        assert spec.minimum <= low and high <= spec.maximum, (prefix, index, signal)
        # and the raw integer holds the whole declared range (no clipping by the bit width)
        raw_min = -(2 ** (spec.length - 1)) if spec.is_signed else 0
        raw_max = 2 ** (spec.length - 1) - 1 if spec.is_signed else 2**spec.length - 1
        assert raw_min * spec.scale <= low and high <= raw_max * spec.scale


def test_kappa_reach_is_the_segment_models_theta_max_over_length() -> None:
    spec = load_spec(model_folder("FeaSegment"))
    theta_max, length = spec.variable("theta_max").start, spec.variable("length").start
    assert theta_max is not None and length is not None
    assert theta_max / length == pytest.approx(KAPPA_REACH, rel=1e-12)
    assert round(KAPPA_REACH, 1) == 26.7


@pytest.mark.parametrize(
    ("frame", "expected"),
    [
        (Sync(256), Sync(0)),
        (Sync(-1), Sync(255)),
        (Sync(256 * 7 + 9), Sync(9)),
        (DriveStatus(1, 0.0, 0.0, 0.0, 0, 300), DriveStatus(1, 0.0, 0.0, 0.0, 0, 44)),
        (DriveCommand(3, 0.0, True, 511), DriveCommand(3, 0.0, True, 255)),
        (ControllerState(8, 0.0, 0.0, 1000), ControllerState(8, 0.0, 0.0, 232)),
        (Emcy(4, 1, 0, 0.0, 256), Emcy(4, 1, 0, 0.0, 0)),
        (CameraMarker(5, 0.0, 0.0, 257, 0.0), CameraMarker(5, 0.0, 0.0, 1, 0.0)),
    ],
)
def test_counters_wrap_modulo_256(protocol: Protocol, frame: Frame, expected: Frame) -> None:
    assert round_trip(protocol, frame) == expected


@pytest.mark.parametrize(
    ("frame", "name", "signal"),
    [
        (DriveCommand(1, -1e-3, True, 0), "DriveCommand1", "piston_setpoint"),
        (DriveCommand(1, 0.2, True, 0), "DriveCommand1", "piston_setpoint"),
        (DriveStatus(2, 0.14, 0.0, 0.0, 0, 0), "DriveStatus2", "piston_position"),
        (DriveStatus(2, 0.05, 4e5, 0.0, 0, 0), "DriveStatus2", "p_a"),
        (DriveStatus(2, 0.05, 0.0, -4e5, 0, 0), "DriveStatus2", "p_b"),
        (DriveStatus(2, 0.05, 0.0, 0.0, 256, 0), "DriveStatus2", "fault"),
        (ControllerState(3, 40.0, 0.0, 0), "ControllerState3", "kappa_ref"),
        (ControllerState(3, 0.0, -40.0, 0), "ControllerState3", "kappa_est"),
        (Emcy(4, 0x10000, 0, 0.0, 0), "EMCY4", "error_code"),
        (Emcy(4, 1, 0, 5e5, 0), "EMCY4", "pressure"),
        (Heartbeat(5, 256), "Heartbeat5", "nmt_state"),
        (CameraMarker(6, 0.7, 0.0, 0, 0.0), "CameraMarker6", '"x"'),
        (CameraMarker(6, 0.0, -0.7, 0, 0.0), "CameraMarker6", '"y"'),
        (CameraMarker(6, 0.0, 0.0, 0, -1e-3), "CameraMarker6", "exposure_offset"),
        (CameraMarker(6, 0.0, 0.0, 0, 0.7), "CameraMarker6", "exposure_offset"),
    ],
)
def test_out_of_range_names_frame_and_signal(
    protocol: Protocol, frame: Frame, name: str, signal: str
) -> None:
    with pytest.raises(FrameError) as info:
        protocol.encode(frame)
    text = str(info.value)
    assert text.startswith(f"{name} (0x{protocol.frame_id(frame):03X}): ")
    assert signal in text
    assert "\n" not in text


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize(
    ("make", "name", "signal"),
    [
        (lambda v: DriveCommand(1, v, True, 0), "DriveCommand1", "piston_setpoint"),
        (lambda v: DriveStatus(8, 0.0, 0.0, v, 0, 0), "DriveStatus8", "p_b"),
        (lambda v: ControllerState(2, 0.0, v, 0), "ControllerState2", "kappa_est"),
        (lambda v: Emcy(1, 1, 0, v, 0), "EMCY1", "pressure"),
        (lambda v: CameraMarker(0, v, 0.0, 0, 0.0), "CameraMarker0", "x"),
        (lambda v: CameraMarker(0, 0.0, 0.0, 0, v), "CameraMarker0", "exposure_offset"),
    ],
)
def test_non_finite_values_are_rejected(
    protocol: Protocol, value: float, make: Callable[[float], Frame], name: str, signal: str
) -> None:
    with pytest.raises(FrameError, match=rf"^{name} \(0x[0-9A-F]{{3}}\): {signal} is "):
        protocol.encode(make(value))


def test_a_frame_without_one_of_its_signals_is_rejected_naming_it(protocol: Protocol) -> None:
    # a generic frame (a kind with no typed class) can lack a signal; it is named, not a KeyError
    frame = GenericFrame("ValveCommand", 2, {"open_time": 0.0125, "counter": 0x33})
    with pytest.raises(FrameError, match=r"^ValveCommand2 \(0x212\): no value for signal vent$"):
        protocol.encode(frame)


@pytest.mark.parametrize(
    ("frame", "message"),
    [
        (DriveStatus(0, 0.0, 0.0, 0.0, 0, 0), "DriveStatus0: no such frame"),
        (DriveCommand(17, 0.0, True, 0), "DriveCommand17: no such frame"),
        (Emcy(0, 0, 0, 0.0, 0), "EMCY0: no such frame"),  # 0x080 is SYNC, not an EMCY
        (Heartbeat(17, 5), "Heartbeat17: no such frame"),
        (CameraMarker(16, 0.0, 0.0, 0, 0.0), "CameraMarker16: no such frame"),
        (CameraMarker(-1, 0.0, 0.0, 0, 0.0), "CameraMarker-1: no such frame"),
    ],
)
def test_node_or_marker_out_of_range(protocol: Protocol, frame: Frame, message: str) -> None:
    with pytest.raises(FrameError, match=f"^{message}"):
        protocol.encode(frame)


@pytest.mark.parametrize(
    ("frame_id", "text"),
    [(0x123, "0x123"), (0x180, "0x180"), (0x2A0, "0x2A0"), (0x711, "0x711"), (0x7FF, "0x7FF")],
)
def test_decoding_an_unknown_id(protocol: Protocol, frame_id: int, text: str) -> None:
    message = can.Message(arbitration_id=frame_id, data=bytes(8), is_extended_id=False)
    with pytest.raises(FrameError, match=f"^unknown CAN id {text}$"):
        protocol.decode(message)


def _with_data(message: can.Message) -> can.Message:
    message.data = bytearray(8)
    return message


@pytest.mark.parametrize(
    "message",
    [
        can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=True),
        can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=8, is_extended_id=False),
        can.Message(arbitration_id=0x181, is_error_frame=True, is_extended_id=False),
        # with the id's length of data, set after python-can built them
        _with_data(can.Message(arbitration_id=0x181, is_remote_frame=True, is_extended_id=False)),
        _with_data(can.Message(arbitration_id=0x181, is_error_frame=True, is_extended_id=False)),
    ],
)
@pytest.mark.parametrize("warm", [False, True])
def test_extended_remote_and_error_frames_are_rejected(message: can.Message, warm: bool) -> None:
    """Also once the id has been decoded before (`decode`'s quick path)."""
    protocol = Protocol()
    if warm:
        protocol.decode(protocol.encode(DriveStatus(1, 0.01, 0.0, 0.0, 0, 0)))
    with pytest.raises(FrameError, match="0x181"):
        protocol.decode(message)


@pytest.mark.parametrize(("frame_id", "length"), [(0x181, 7), (0x181, 0), (0x201, 5), (0x701, 2)])
def test_wrong_data_length(protocol: Protocol, frame_id: int, length: int) -> None:
    message = can.Message(arbitration_id=frame_id, data=bytes(length), is_extended_id=False)
    expected = protocol.message(frame_id).length
    with pytest.raises(FrameError) as info:
        protocol.decode(message)
    assert str(info.value) == (
        f"{protocol.message(frame_id).name} (0x{frame_id:03X}): {length} data bytes, "
        f"the DBC says {expected}"
    )


def derived_frame_bits(dlc: int) -> int:
    """Classic CAN data frame, 11-bit id, worst-case stuffing, counted field by field."""
    sof, identifier, rtr, ide, r0, dlc_field = 1, 11, 1, 1, 1, 4
    data = 8 * dlc
    crc, crc_delimiter, ack, ack_delimiter, eof, intermission = 15, 1, 1, 1, 7, 3
    stuffed = sof + identifier + rtr + ide + r0 + dlc_field + data + crc  # 34 + 8 dlc
    frame = stuffed + crc_delimiter + ack + ack_delimiter + eof  # 44 + 8 dlc
    # worst case: a stuff bit after the first 5 equal bits, then one per 4 (the stuff bit
    # itself starts the next run of 5)
    stuff_bits = (stuffed - 1) // 4
    return frame + intermission + stuff_bits


def test_frame_bits_textbook_values() -> None:
    assert derived_frame_bits(8) == 135
    assert derived_frame_bits(1) == 65
    assert frame_bits(8) == 135
    assert frame_bits(1) == 65
    assert frame_bits(0) == 55
    assert [frame_bits(n) for n in range(9)] == [derived_frame_bits(n) for n in range(9)]


def test_bus_load(protocol: Protocol) -> None:
    assert bus_load({"DriveStatus1": 1000.0}, 1_000_000, protocol) == 0.135
    # 4-byte command: 47 + 32 + 65 // 4 = 95 bits; loads add
    assert bus_load({"DriveCommand1": 1000.0}, 1_000_000, protocol) == pytest.approx(
        0.095, rel=1e-15
    )
    both = bus_load({"DriveStatus1": 1000.0, "DriveCommand1": 1000.0}, 500_000, protocol)
    assert both == pytest.approx(2 * (0.135 + 0.095), rel=1e-15)
    assert bus_load({}, 1_000_000, protocol) == 0.0


def test_candump_log_written_by_python_can_decodes_with_cantools(
    protocol: Protocol, tmp_path: Path
) -> None:
    frame = DriveStatus(2, 0.05, 1000.0, -2000.0, fault=3, counter=17)
    message = protocol.encode(frame, timestamp=1.25)
    path = tmp_path / "drive.log"
    writer = can.CanutilsLogWriter(path, channel="vcan0")
    writer.on_message_received(message)
    writer.stop()
    text = path.read_text()
    assert text.startswith("(1.250000) vcan0 182#")

    parsed = list(cantools.logreader.Parser(io.StringIO(text)))
    assert len(parsed) == 1
    assert parsed[0].frame_id == 0x182
    assert bytes(parsed[0].data) == bytes(message.data)
    database = cantools.database.load_file(str(DBC_PATH))
    assert isinstance(database, Database)
    decoded = database.decode_message(parsed[0].frame_id, parsed[0].data)
    assert isinstance(decoded, dict)
    assert decoded["piston_position"] == pytest.approx(0.05, abs=1e-6)
    assert decoded["p_a"] == 1000
    assert decoded["p_b"] == -2000
    assert (decoded["fault"], decoded["counter"]) == (3, 17)
    piston = decoded["piston_position"]
    assert isinstance(piston, float)
    assert protocol.decode(message) == DriveStatus(2, piston, 1000.0, -2000.0, 3, 17)


@pytest.mark.parametrize("warm", [False, True])
def test_marker_frame_whose_id_disagrees_with_its_can_id_is_rejected(warm: bool) -> None:
    """Also once the id has been decoded before (`decode`'s quick path: the C codec declines,
    the Python path says why)."""
    protocol = Protocol()
    if warm:
        genuine = protocol.encode(CameraMarker(3, 0.1, 0.2, 1, 0.006))
        assert protocol.decode(genuine) == protocol.decode(genuine)
    message = protocol.encode(CameraMarker(5, 0.1, 0.2, 1, 0.006))
    forged = can.Message(arbitration_id=0x283, data=message.data, is_extended_id=False)
    with pytest.raises(FrameError, match=r"CameraMarker3 \(0x283\): marker_id 5 does not match"):
        protocol.decode(forged)


def test_compiled_codec_equals_cantools_byte_for_byte(protocol: Protocol) -> None:
    """The precompiled codec encodes every message exactly as cantools does (strict), rejects
    exactly the out-of-range values cantools rejects, and decodes every payload the same."""
    rng = np.random.default_rng(7)
    for message in protocol.database.messages:
        codec = protocol._by_name[message.name].codec
        assert codec.compiled, message.name
        for _ in range(60):
            values: dict[str, float] = {}
            for s in message.signals:
                lo, hi = s.minimum, s.maximum
                v = float(rng.choice([lo, hi, rng.uniform(lo, hi)]))
                if s.scale == 1 and s.offset == 0:
                    v = int(round(v))
                if rng.random() < 0.1:  # out of range (a named raw value passes, as in cantools)
                    v += (hi - lo) * 0.5 * float(rng.choice([-1.0, 1.0]))
                elif rng.random() < 0.1:  # at the edge: cantools allows a millionth of the scale
                    margin = abs(s.scale) * float(rng.choice([0.5e-6, 2e-6]))
                    v = float(rng.choice([lo - margin, hi + margin]))
                values[s.name] = v
            try:
                expected: bytes | None = message.encode(values, strict=True)
            except Exception:
                expected = None
            try:
                got: bytes | None = codec.encode(codec.values_of(values))
            except FrameError:
                got = None
            assert got == expected, (message.name, values)
        for _ in range(30):
            data = bytes(rng.integers(0, 256, message.length).tolist())
            want = message.decode(data, decode_choices=False)
            have = codec.as_mapping(codec.decode(data))
            assert have == want and all(type(have[k]) is type(want[k]) for k in want)


OFFSET_DBC = """VERSION ""
NS_ :
BS_:
BU_: Rig
BO_ 256 Offsets: 8 Rig
 SG_ temperature : 0|16@1- (0.01,-40) [-100|250] "degC" Rig
 SG_ level : 16|12@1+ (0.5,10.5) [10.5|2000] "mm" Rig
 SG_ trim : 28|8@1- (1,-3) [-100|100] "" Rig
 SG_ gain : 36|20@1+ (0.001,0) [0|1000] "" Rig
"""


def test_codec_handles_offsets_as_cantools_does() -> None:
    """Our DBC's signals all have offset 0; a user's DBC may not: integer and fractional
    offsets, signed and unsigned, encode and decode as cantools does (this layout, signals
    across byte boundaries, through cantools itself; tests/test_codec.py has offsets in the
    struct)."""
    database = cantools.database.load_string(OFFSET_DBC, strict=True)
    message = database.get_message_by_name("Offsets")
    codec = MessageCodec(message)
    rng = np.random.default_rng(13)
    for _ in range(400):
        values = {
            s.name: float(rng.uniform(s.minimum, s.maximum))
            if rng.random() < 0.8
            else float(rng.choice([s.minimum, s.maximum]))
            for s in message.signals
        }
        assert codec.encode(codec.values_of(values)) == message.encode(values, strict=True)
        data = bytes(rng.integers(0, 256, message.length).tolist())
        assert codec.as_mapping(codec.decode(data)) == message.decode(data, decode_choices=False)


def test_checked_encoding_equals_the_uncompiled_path(protocol: Protocol) -> None:
    """`Protocol.encode` through a message's struct gives what its uncompiled path (the same
    checks in Python, then cantools) gives, bytes or error line, for every message and
    for the values a frame can carry: floats in and out of range, NaN and infinities, ints,
    bools, wrapping counters past their modulus, a missing signal."""
    rng = np.random.default_rng(11)
    specials = [math.nan, math.inf, -math.inf, True, False, -0.0, 256, 257, -1, 10**20]
    compared = failures = 0
    for message in protocol.database.messages:
        entry = protocol._by_name[message.name]
        assert entry.codec.compiled, message.name
        plain = dataclasses.replace(entry, codec=MessageCodec(message, compiled=False))
        for trial in range(80):
            values: dict[str, object] = {}
            for s in message.signals:
                lo, hi = float(s.minimum), float(s.maximum)
                pick = rng.random()
                if pick < 0.5:
                    v: object = float(rng.uniform(lo, hi))
                elif pick < 0.65:
                    v = float(rng.choice([lo, hi]))
                elif pick < 0.7:
                    v = float(rng.uniform(lo, hi) + (hi - lo) * rng.choice([-0.6, 0.6]))
                elif pick < 0.75:  # at the edge of cantools' tolerance, inside or outside
                    margin = abs(s.scale) * float(rng.choice([0.5e-6, 2e-6]))
                    v = float(rng.choice([lo - margin, hi + margin]))
                elif pick < 0.85:
                    v = int(rng.integers(int(lo), int(hi) + 2))
                else:
                    v = specials[int(rng.integers(len(specials)))]
                values[s.name] = v
            if trial % 20 == 19:
                del values[message.signals[int(rng.integers(len(message.signals)))].name]
            outcomes = []
            for e in (entry, plain):
                protocol._by_name[message.name] = protocol._by_id[message.frame_id] = e
                protocol._by_key[(e.kind, e.index)] = e
                try:
                    frame = GenericFrame(e.kind, e.index, values)
                    outcomes.append(bytes(protocol.encode(frame).data))
                except FrameError as exc:
                    outcomes.append(str(exc))
                finally:
                    protocol._by_name[message.name] = protocol._by_id[message.frame_id] = entry
                    protocol._by_key[(entry.kind, entry.index)] = entry
            assert outcomes[0] == outcomes[1], (message.name, values)
            compared += 1
            failures += isinstance(outcomes[0], str)
    # both outcomes were exercised: frames encoded and frames refused
    assert 0.2 < failures / compared < 0.9, (failures, compared)


# Golden bytes: one frame of every kind in the DBC, encoded by hand from the DBC's layout
# (little-endian, raw = value / scale, two's complement for signed signals). The values are
# distinct in every byte, so a moved, resized, swapped or rescaled signal changes the bytes.
GOLDEN: list[tuple[Frame, int, str]] = [
    (Sync(0xA5), 0x080, "A5"),
    # piston 0.0123 m = 6150 * 2e-6 (0x1806), p_a 1230 Pa = 123 (0x007B), p_b -4560 Pa =
    # -456 (0xFE38), fault 0x12, counter 0xC7
    (DriveStatus(3, 0.0123, 1230.0, -4560.0, 0x12, 0xC7), 0x183, "06187B0038FE12C7"),
    # setpoint 0.0456 m = 22800 (0x5910), enable at bit 16, counter 0x3C
    (DriveCommand(3, 0.0456, True, 0x3C), 0x203, "1059013C"),
    # kappa_ref 12.345 1/m = 12345 (0x3039), kappa_est -6.789 = -6789 (0xE57B), counter 0x4D
    (ControllerState(3, 12.345, -6.789, 0x4D), 0x383, "39307BE54D"),
    # error code 0xFF01, register 0x81, pressure 12340 Pa = 1234 (0x04D2), counter 0x2A
    (Emcy(3, EMCY_OVER_PRESSURE, 0x81, 12340.0, 0x2A), 0x083, "01FF81D2042A"),
    (Heartbeat(3, NMT_OPERATIONAL), 0x703, "05"),
    # marker 4, x 0.1234 m = 6170 (0x181A), y -0.0567 = -2835 (0xF4ED), frame 0x9B,
    # exposure offset 0.006 s = 600 (0x0258)
    (CameraMarker(4, 0.1234, -0.0567, 0x9B, 0.006), 0x284, "041A18EDF49B5802"),
    # frame 0x11, x 0.01 m = 500 (0x01F4), y -0.02 = -1000 (0xFC18), z 0.3 = 15000 (0x3A98)
    (CameraMarker3D(5, 0x11, 0.01, -0.02, 0.3), 0x295, "11F40118FC983A00"),
    # frame 0x22, exposure offset 0.016 s = 1600 (0x0640), mask 0b1011, 3 markers
    (CameraFrame(0x22, 0.016, 0b1011, 3), 0x27F, "2240060B00030000"),
    # open 12.5 ms = 125 (0x007D), vent at bit 16, counter 0x33
    (
        GenericFrame("ValveCommand", 2, {"open_time": 0.0125, "vent": 1, "counter": 0x33}),
        0x212,
        "7D000133",
    ),
    # state 2, channel -2500 Pa = -250 (0xFF06), fault 0x10 at byte 3, counter 0x44 at byte 5
    (
        GenericFrame(
            "ValveStatus", 2, {"state": 2, "p_channel": -2500.0, "fault": 0x10, "counter": 0x44}
        ),
        0x192,
        "0206FF100044",
    ),
    # canister 4.5 MPa = 45000 * 100 (0xAFC8), supply 350 kPa = 35000 * 10 (0x88B8),
    # gas left 32.1 g = 32100 * 1e-6 kg (0x7D64), counter 0x55
    (
        GenericFrame(
            "CanisterStatus",
            None,
            {"p_canister": 4.5e6, "p_supply": 350e3, "gas_left": 0.0321, "counter": 0x55},
        ),
        0x1A0,
        "C8AFB888647D0055",
    ),
    # counter 0x9C, target 0x0102 (little endian), phase 5 (tracking), x 0.1234 m = 6170
    # (0x181A), y -0.0567 m = -2835 (0xF4ED)
    (TaskState(0x0102, 5, 0.1234, -0.0567, 0x9C), 0x3F0, "9C0201051A18EDF4"),
    # spatial task state: goal 7, phase 3 (settled), x 0.1234 m = 6170 (0x181A), y -0.0567 m
    # = -2835 (0xF4ED), z 0.3 m = 15000 (0x3A98)
    (SpatialTaskState(7, 3, 0.1234, -0.0567, 0.3), 0x3F2, "07031A18EDF4983A"),
    # fish state: mode 4 (hold), manoeuvre 0x12, heading_ref 1.0472 rad = 10472 (0x28E8),
    # heading_est -0.5 rad = -5000 (0xEC78), 200 manoeuvres left (0xC8), counter 0x9D
    (
        GenericFrame(
            "FishState",
            None,
            {
                "mode": 4,
                "manoeuvre": 0x12,
                "heading_ref": 1.0472,
                "heading_est": -0.5,
                "manoeuvres_left": 200,
                "counter": 0x9D,
            },
        ),
        0x3F1,
        "0412E82878ECC89D",
    ),
]


def test_golden_bytes_cover_every_kind_in_the_dbc(protocol: Protocol) -> None:
    kinds = {message.name.rstrip("0123456789") for message in protocol.database.messages}
    assert {frame_key(frame)[0] for frame, _, _ in GOLDEN} == kinds


@pytest.mark.parametrize(
    ("frame", "frame_id", "data"), GOLDEN, ids=[frame_key(f)[0] for f, _, _ in GOLDEN]
)
def test_golden_bytes_of_every_message_kind(
    protocol: Protocol, frame: Frame, frame_id: int, data: str
) -> None:
    message = protocol.encode(frame)
    assert (message.arbitration_id, bytes(message.data).hex().upper()) == (frame_id, data)
    # and the bytes decode to the frame, every signal within half its scaling step
    wire = can.Message(arbitration_id=frame_id, data=bytes.fromhex(data), is_extended_id=False)
    back = protocol.decode(wire)
    assert frame_key(back) == frame_key(frame)
    declared = protocol.message(frame_id)
    expected, got = frame_signals(frame), frame_signals(back)
    assert set(got) == set(expected)
    for name, value in expected.items():
        assert close(got[name], value, declared.get_signal_by_name(name).scale), name


def test_exact_multiples_of_a_scale_encode_to_their_integer(protocol: Protocol) -> None:
    """k * scale encodes to raw k exactly (cantools' exact-quotient path), for scales that are
    not binary fractions: rounding after a float division would be off by one for some k."""
    message = protocol.message_by_name("DriveCommand1")
    codec = protocol._by_name["DriveCommand1"].codec
    assert codec.compiled
    scale = message.get_signal_by_name("piston_setpoint").scale
    for k in range(0, 50_001, 7):
        value = k * scale
        data = codec.encode(codec.values_of({"piston_setpoint": value, "enable": 1, "counter": 0}))
        assert int.from_bytes(data[:2], "little") == k, k
        assert data == message.encode(
            {"piston_setpoint": value, "enable": 1, "counter": 0}, strict=True
        )


def test_a_frame_finds_its_message_the_same_way_the_second_time() -> None:
    """`Protocol.encode` remembers the message of a typed frame class and int index; a frame
    met later with an index equal to it, or one int() turns into it, or a bad one, gets what a
    fresh protocol gives it: the same bytes, or the same error."""
    values = dict(piston_position=0.0123, p_a=1230.0, p_b=-4560.0, fault=0x12, counter=0xC7)
    indices: list[object] = [3, 3, 3.0, True, np.int64(4), 4.5, "5", 9, 0, -1, None, [3], 2**70]
    warm = Protocol()
    for index in indices:
        outcomes = []
        for protocol in (warm, Protocol()):
            try:
                message = protocol.encode(DriveStatus(index, **values))  # type: ignore[arg-type]
                outcomes.append((message.arbitration_id, bytes(message.data)))
            except (FrameError, TypeError, ValueError, OverflowError) as exc:
                outcomes.append((type(exc).__name__, str(exc)))
        assert outcomes[0] == outcomes[1], index
    assert warm.encode(DriveStatus(3.0, **values)).arbitration_id == 0x183  # type: ignore[arg-type]
    with pytest.raises(FrameError, match=r"DriveStatus17: no such frame"):
        warm.encode(DriveStatus(17, **values))


@pytest.mark.parametrize("maker", ["python", "c"])
@pytest.mark.parametrize("data", [b"", b"\x01\x02\x03", bytes(range(8))])
def test_data_message_is_can_message_field_for_field(data: bytes, maker: str) -> None:
    """The encoder's quick `can.Message` (no checks to pass again), made in Python or in C
    (`rigbus.canbus.c_messages`), has every field python-can's constructor gives, of the
    same types; the encoder uses the C one where the C codec is in use."""
    from rigbus.canbus import c_messages
    from rigbus.protocol import data_message

    if maker == "c":
        module = c_messages()
        if module is None:
            pytest.skip("no C codec here")
        data_message = module.data_message
        assert Protocol()._data_message is data_message
    quick = data_message(0x181, data, 1433116800.25)
    made = can.Message(
        arbitration_id=0x181, data=data, is_extended_id=False, timestamp=1433116800.25
    )
    fields = [name for name in can.Message.__slots__ if name != "__weakref__"]
    assert len(fields) == 12
    for name in fields:
        assert getattr(quick, name) == getattr(made, name), name
        assert type(getattr(quick, name)) is type(getattr(made, name)), name
    assert quick.equals(made, check_channel=True, check_direction=True)


def test_protocols_share_one_checked_layout_until_a_frame_type_is_registered() -> None:
    """The DBC's entries are made and checked once per registry state: every Protocol shares
    them, and a type registered later (a robot's plug-in) is checked by the next Protocol."""
    from rigbus import protocol as module

    first, second = Protocol(), Protocol()
    assert first._by_id is second._by_id and first._by_key is second._by_key
    saved = module._REGISTRY["Heartbeat"]
    try:

        @module.frame_type("Heartbeat", index="node")
        @dataclasses.dataclass(frozen=True, slots=True)
        class Wrong:
            node: int
            nmt_status: int  # the DBC's signal is nmt_state

        with pytest.raises(FrameError, match=r"Heartbeat\d*: the DBC's signals .*nmt_state"):
            Protocol()
    finally:
        module._REGISTRY["Heartbeat"] = saved
        module._REGISTERED[0] += 1
    third = Protocol()
    assert third._by_id is not first._by_id
    assert third.decode(third.encode(Heartbeat(node=3, nmt_state=5))) == Heartbeat(3, 5)
