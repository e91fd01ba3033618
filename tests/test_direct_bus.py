"""The synchronous in-process bus pair (`hil.bus.direct`): what one end sends reaches the other
as a copy (a later change to the sent message changes nothing delivered), in order, with every
field kept; python-can's filters still apply on receive."""

from __future__ import annotations

import can

from hil.bus.direct import direct_pair


def test_frames_arrive_in_order_as_copies_with_every_field() -> None:
    plant, controller = direct_pair("t")
    sent = [
        can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False, timestamp=2.5),
        can.Message(arbitration_id=0x1ABCDE, data=b"\xff" * 8, is_extended_id=True, is_rx=False),
        can.Message(arbitration_id=0x7, is_remote_frame=True, dlc=3, is_extended_id=False),
        can.Message(
            arbitration_id=0x9,
            data=bytes(12),
            is_fd=True,
            bitrate_switch=True,
            error_state_indicator=True,
            is_extended_id=False,
        ),
    ]
    for message in sent:
        plant.send(message)
    sent[0].data[0] = 0x55  # the sender reuses its message: the frame on the bus is unchanged
    got = [controller.recv(0.0) for _ in sent]
    assert controller.recv(0.0) is None
    for g, s in zip(got, sent, strict=True):
        assert g is not s and g.channel == "direct:t/controller"
        for field in (
            "timestamp",
            "arbitration_id",
            "is_extended_id",
            "is_remote_frame",
            "is_error_frame",
            "dlc",
            "is_fd",
            "is_rx",
            "bitrate_switch",
            "error_state_indicator",
        ):
            assert getattr(g, field) == getattr(s, field), field
        assert isinstance(g.data, bytearray)
    assert got[0].data == bytearray(b"\x01\x02")
    assert got[1].data == bytearray(b"\xff" * 8) and got[3].data == bytearray(12)


def test_a_handler_gets_each_frame_at_once_and_filters_apply_on_receive() -> None:
    plant, controller = direct_pair("h")
    seen: list[can.Message] = []
    plant.handler = seen.append
    controller.send(can.Message(arbitration_id=0x80, data=b"\x01", is_extended_id=False))
    assert [m.arbitration_id for m in seen] == [0x80] and seen[0].channel == "direct:h/plant"
    controller.set_filters([{"can_id": 0x200, "can_mask": 0x700, "extended": False}])
    for can_id in (0x181, 0x201, 0x382, 0x2FF):
        plant.send(can.Message(arbitration_id=can_id, data=b"", is_extended_id=False))
    assert [controller.recv(0.05).arbitration_id for _ in range(2)] == [0x201, 0x2FF]
    assert controller.recv(0.0) is None
