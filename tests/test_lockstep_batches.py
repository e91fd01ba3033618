"""In lockstep, on a bus that sends batches, the controller sends a cycle's commands together
with the next SYNC in one batch: they must still reach the plant before that SYNC, so the plant
latches them at SYNC(c + 1) exactly as when they were sent one by one right after they were
computed. The in-process direct bus is given a `send_batch` here (it has none: batching would
save nothing there) that records the batches and delivers their frames in order."""

from __future__ import annotations

from pathlib import Path

import can
import pytest

import hil.run
from hil.bus.direct import DirectBus, direct_pair
from hil.run import RunOptions, run_scenario
from hil.scenario import DEFAULT_SCENARIO, load_scenario

SYNC, COMMAND, STATE = 0x080, 0x201, 0x381  # SYNC, DriveCommand1, ControllerState1


class BatchingBus(DirectBus):
    batches: list[list[int]]

    def send_batch(self, messages: list[can.Message]) -> None:
        self.batches.append([m.arbitration_id for m in messages])
        for message in messages:
            self.send(message)


def test_each_cycles_commands_reach_the_plant_before_the_next_sync(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    batches: list[list[int]] = []

    def pair(name: str) -> tuple[DirectBus, DirectBus]:
        plant, controller = direct_pair(name)
        controller.__class__ = BatchingBus
        controller.batches = batches  # type: ignore[attr-defined]
        return plant, controller

    monkeypatch.setattr(hil.run, "direct_pair", pair)
    text = DEFAULT_SCENARIO.read_text().replace("duration = 10.0", "duration = 0.2")
    assert "duration = 0.2" in text
    (tmp_path / "s.toml").write_text(text)
    out = tmp_path / "run"
    run_scenario(
        load_scenario(tmp_path / "s.toml"), RunOptions(out=out, inprocess=True, progress=False)
    )
    received = [
        (m.arbitration_id, m.data[-1])  # all three carry their counter in the last byte
        for m in can.LogReader(str(out / "can.log"))
        if m.is_rx
    ]
    assert {can_id for can_id, _ in received} == {SYNC, COMMAND, STATE}
    syncs = [i for i, (can_id, _) in enumerate(received) if can_id == SYNC]
    assert [received[i][1] for i in syncs] == list(range(21))
    # between SYNC(c) and SYNC(c + 1): exactly the command and the state computed at SYNC(c)
    for c, (begin, end) in enumerate(zip(syncs, syncs[1:], strict=False)):
        assert sorted(received[begin + 1 : end]) == [(COMMAND, c), (STATE, c)], c
    # one batch a cycle: the previous cycle's command and state, then the SYNC
    assert batches[0] == [SYNC]
    assert batches[1:] == [[COMMAND, STATE, SYNC]] * 20
