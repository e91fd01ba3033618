"""The CAN log's candump lines, written by hil.recording.CanLogger (the one candump writer: every
kind of frame, held as logged and written at each flush), are python-can's CanutilsLogWriter's
lines byte for byte."""

from __future__ import annotations

import random
from pathlib import Path

import can
import pytest

from hil.recording import CanLogger
from rigbus.protocol import frame_bits

FD_LENGTHS = (12, 16, 20, 24, 32, 48, 64)


def _message(rng: random.Random, i: int) -> can.Message:
    """Mostly classic data frames; some remote, error and FD frames, which python-can writes."""
    extended = rng.random() < 0.3
    kind = rng.random()
    fd = kind > 0.9
    return can.Message(
        arbitration_id=rng.randrange(0x20000000 if extended else 0x800),
        is_extended_id=extended,
        is_remote_frame=kind < 0.05,
        is_error_frame=0.05 <= kind < 0.08,
        is_fd=fd,
        bitrate_switch=fd and rng.random() < 0.5,
        error_state_indicator=fd and rng.random() < 0.5,
        dlc=3 if kind < 0.05 else None,
        data=None
        if kind < 0.05
        else bytes(rng.randrange(256) for _ in range(rng.choice(FD_LENGTHS) if fd else i % 9)),
    )


def test_candump_lines_are_python_cans_byte_for_byte(tmp_path: Path) -> None:
    rng = random.Random(3)
    start = 1433116800.0
    times = [0.0, *sorted(rng.uniform(0.0, 30.0) for _ in range(200))]
    times[50] = -0.25  # before the first stamp: the writer writes the first stamp instead
    times[100:100] = [times[99]] * 5  # frames sharing a stamp, as a SYNC's do
    times[151:151] = [-0.25] * 3
    logger = CanLogger(tmp_path / "ours.log", start=start)
    reference = tmp_path / "reference.log"
    frames = bits = 0
    with reference.open("w") as file:
        writer = can.CanutilsLogWriter(file)
        for i, t in enumerate(times):
            message = _message(rng, i)
            received = rng.random() < 0.5
            if i % 7 == 0:  # a SYNC's frames, logged together
                batch = [message, _message(rng, i + 1), _message(rng, i + 2)]
            else:
                batch = [message]
            if len(batch) > 1:
                logger.log_all(batch, t, received=received)
            else:
                logger.log(message, t, received=received)
            for m in batch:
                writer.on_message_received(
                    can.Message(
                        timestamp=start + t,
                        arbitration_id=m.arbitration_id,
                        is_extended_id=m.is_extended_id,
                        is_remote_frame=m.is_remote_frame,
                        is_error_frame=m.is_error_frame,
                        is_fd=m.is_fd,
                        bitrate_switch=m.bitrate_switch,
                        error_state_indicator=m.error_state_indicator,
                        dlc=m.dlc,
                        data=None if m.is_remote_frame else bytes(m.data),
                        is_rx=received,
                        channel="can0",
                    )
                )
                frames += 1
                bits += frame_bits(len(m.data))
    logger.close()
    assert (tmp_path / "ours.log").read_bytes() == reference.read_bytes()
    assert logger.sent + logger.received == frames
    assert logger.bits == bits
    text = reference.read_text()
    assert " R\n" in text and "R T\n" in text and "##" in text  # every kind was written


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


def test_a_remote_frame_after_a_later_one_keeps_its_stamp(tmp_path: Path) -> None:
    """A frame stamped before the one logged before it keeps its stamp: only a stamp before the
    log's first is moved (to the first), as python-can's writer does."""
    logger = CanLogger(tmp_path / "x.log", start=0.0)
    data = can.Message(arbitration_id=0x80, is_extended_id=False, data=b"\x07")
    remote = can.Message(arbitration_id=0x81, is_extended_id=False, is_remote_frame=True, dlc=1)
    logger.log(data, 0.0, False)
    logger.log(remote, 5.0, True)
    logger.log(remote, 1.0, True)
    logger.close()
    assert (tmp_path / "x.log").read_text().splitlines() == [
        "(0.000000) can0 080#07 T",
        "(5.000000) can0 081#R R",
        "(1.000000) can0 081#R R",
    ]


def test_frames_held_by_log_are_written_in_order_and_on_flush(tmp_path: Path) -> None:
    """`log` holds the frames of one time and direction and writes them together: before any
    frame logged otherwise (`log_all`, another time or direction), and on `flush` (the file has
    them then, not only when closed), in the order they were logged."""
    frames = [
        can.Message(arbitration_id=0x100 + k, is_extended_id=False, data=bytes([k]))
        for k in range(6)
    ]
    logger = CanLogger(tmp_path / "x.log", start=100.0)
    logger.log(frames[0], 0.01, True)
    logger.log_all(frames[1:3], 0.01, True)  # the same time and direction: after frame 0
    logger.log(frames[3], 0.01, True)
    logger.log(frames[4], 0.01, False)  # another direction
    logger.flush()  # not FLUSH_INTERVAL since the logger opened: held still
    assert (tmp_path / "x.log").read_bytes() == b""
    logger.flush(force=True)
    lines = (tmp_path / "x.log").read_text().splitlines()
    assert [line.split()[2][:3] for line in lines] == ["100", "101", "102", "103", "104"]
    assert [line[-1] for line in lines] == ["R", "R", "R", "R", "T"]
    logger.log(frames[5], 0.02, True)
    assert (logger.sent, logger.received) == (1, 4)  # counted when written
    logger.close()
    assert (tmp_path / "x.log").read_text().splitlines()[-1] == "(100.020000) can0 105#05 R"
    assert (logger.sent, logger.received) == (1, 5)


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".trc"])
def test_python_can_formats_read_back_with_stamps_directions_and_frames(
    tmp_path: Path, suffix: str
) -> None:
    """The other suffixes go through python-can's writers at each flush: read back with
    python-can's readers, every frame is there in order with its stamp, direction and data."""
    rng = random.Random(6)
    start = 1433116800.0
    logged = []
    logger = CanLogger(tmp_path / f"x{suffix}", start=start)
    for k in range(40):
        message = can.Message(
            arbitration_id=rng.randrange(0x800),
            is_extended_id=False,
            data=bytes(rng.randrange(256) for _ in range(rng.randrange(9))),
        )
        received = k % 3 == 0
        if k % 2:
            logger.log(message, k * 0.01, received)
        else:
            logger.log_all([message], k * 0.01, received)
        logged.append((start + k * 0.01, received, message.arbitration_id, bytes(message.data)))
        if k % 10 == 9:
            logger.flush(force=True)
    logger.close()
    read = [
        (m.timestamp, m.is_rx, m.arbitration_id, bytes(m.data))
        for m in can.LogReader(str(tmp_path / f"x{suffix}"))
    ]
    assert [r[1:] for r in read] == [w[1:] for w in logged]
    # stamps as each reader gives them (absolute, or from the log's start): the same steps
    assert [r[0] - read[0][0] for r in read] == pytest.approx(
        [w[0] - start for w in logged], abs=1e-4
    )
    assert (logger.sent, logger.received) == (26, 14)
