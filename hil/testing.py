"""pytest support: turn recorded runs into regression tests for a controller.

Installed with softhil as a pytest plugin, it gives the fixture `softhil_replay`, which is
`hil.replay.assert_replays`:

    def test_my_controller_still_does_what_it_did(softhil_replay):
        softhil_replay("tests/runs/step-response/can.log")

It replays the log's plant frames to the controller of the run's controller.json (or the
configuration you pass) and fails on the first diverging cycle, message and signal. Your own
controller program replays the same way, by its command line (`hil.program`):

    softhil_replay("tests/runs/mine/can.log", controller="python my_ctrl.py --bus {bus}")
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest


@pytest.fixture
def softhil_replay() -> Callable[..., Any]:
    from hil.replay import assert_replays

    return assert_replays
