"""The CAN log's candump lines, written by hil.recording.CanLogger without python-can's writer
on the hot path, are python-can's CanutilsLogWriter's lines byte for byte."""

from __future__ import annotations

import random
from pathlib import Path

import can

from hil.recording import CanLogger


def test_candump_lines_are_python_cans_byte_for_byte(tmp_path: Path) -> None:
    rng = random.Random(3)
    start = 1433116800.0
    times = [0.0, *sorted(rng.uniform(0.0, 30.0) for _ in range(200))]
    times[50] = -0.25  # before the first stamp: the writer writes the first stamp instead
    times[100:100] = [times[99]] * 5  # frames sharing a stamp, as a SYNC's do
    times[151:151] = [-0.25] * 3
    logger = CanLogger(tmp_path / "ours.log", start=start)
    reference = tmp_path / "reference.log"
    with reference.open("w") as file:
        writer = can.CanutilsLogWriter(file)
        for i, t in enumerate(times):
            extended = rng.random() < 0.3
            message = can.Message(
                arbitration_id=rng.randrange(0x20000000 if extended else 0x800),
                is_extended_id=extended,
                data=bytes(rng.randrange(256) for _ in range(i % 9)),
            )
            received = rng.random() < 0.5
            logger.log(message, t, received=received)
            writer.on_message_received(
                can.Message(
                    timestamp=start + t,
                    arbitration_id=message.arbitration_id,
                    is_extended_id=extended,
                    data=bytes(message.data),
                    is_rx=received,
                    channel="can0",
                )
            )
    logger.close()
    assert (tmp_path / "ours.log").read_bytes() == reference.read_bytes()
    assert logger.sent + logger.received == len(times)


def test_a_numeric_channel_is_written_as_python_can_writes_it(tmp_path: Path) -> None:
    logger = CanLogger(tmp_path / "x.log", start=0.0, channel="1")
    logger.log(can.Message(arbitration_id=0x80, is_extended_id=False, data=b"\x07"), 0.5, True)
    logger.close()
    assert (tmp_path / "x.log").read_text() == "(0.500000) can1 080#07 R\n"


def test_frames_sharing_a_stamp_and_signed_zeros(tmp_path: Path) -> None:
    """A SYNC's frames share a stamp (formatted once); a stamp of -0.0 is written as such."""
    lines = []
    for start, times in ((0.0, [0.0, -0.0, -0.0, 0.0, 0.5, 0.5]), (-0.0, [-0.0, 0.0, 0.0])):
        logger = CanLogger(tmp_path / "x.log", start=start)
        for t in times:
            message = can.Message(arbitration_id=0x80, is_extended_id=False, data=b"\x07")
            logger.log(message, t, False)
        logger.close()
        lines.append((tmp_path / "x.log").read_text())
        reference = tmp_path / "reference.log"
        with reference.open("w") as file:
            writer = can.CanutilsLogWriter(file)
            for t in times:
                writer.on_message_received(
                    can.Message(
                        timestamp=start + t,
                        arbitration_id=0x80,
                        is_extended_id=False,
                        data=b"\x07",
                        is_rx=False,
                        channel="can0",
                    )
                )
        assert lines[-1] == reference.read_text()
    assert lines[0].splitlines()[:2] == ["(0.000000) can0 080#07 T"] * 2


def test_frames_logged_together_are_the_lines_of_frames_logged_one_by_one(
    tmp_path: Path,
) -> None:
    """`log_all` (a SYNC's frames, sent at once) writes what `log` writes for each in turn, and
    counts them alike, in a candump log and in a format python-can's writer writes."""
    rng = random.Random(4)
    groups = []
    for k in range(60):
        t = -0.25 if k == 7 else k * 0.01 + (0.005 if k % 5 == 0 else 0.0)
        messages = [
            can.Message(
                arbitration_id=rng.randrange(0x800),
                is_extended_id=False,
                data=bytes(rng.randrange(256) for _ in range(rng.randrange(9))),
            )
            for _ in range(rng.randrange(4))  # none, now and then
        ]
        groups.append((messages, t, rng.random() < 0.5))
    for suffix in (".log", ".asc"):
        one, together = (
            CanLogger(tmp_path / f"one{suffix}", 1e9),
            CanLogger(tmp_path / f"together{suffix}", 1e9),
        )
        for messages, t, received in groups:
            for message in messages:
                one.log(message, t, received)
            together.log_all(messages, t, received)
        one.close()
        together.close()
        assert (tmp_path / f"one{suffix}").read_bytes() == (
            tmp_path / f"together{suffix}"
        ).read_bytes()
        assert (one.sent, one.received, one.bits) == (
            together.sent,
            together.received,
            together.bits,
        )
        assert one.sent > 20 and one.received > 20
