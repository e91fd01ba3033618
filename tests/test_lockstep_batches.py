"""In lockstep the controller sends a cycle's commands together with the next SYNC (one write
where the bus can): they must still reach the plant before that SYNC, so the plant latches them
at SYNC(c + 1) exactly as when they were sent one by one right after they were computed."""

from __future__ import annotations

from pathlib import Path

import can

from hil.run import RunOptions, run_scenario
from hil.scenario import DEFAULT_SCENARIO, load_scenario

SYNC, COMMAND, STATE = 0x080, 0x201, 0x381  # SYNC, DriveCommand1, ControllerState1


def test_each_cycles_commands_reach_the_plant_before_the_next_sync(tmp_path: Path) -> None:
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
