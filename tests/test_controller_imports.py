"""The controller never imports the plant (`controllers/__init__.py`): every module of the
controller side, its C codec built and used, loads no `hil` module; opening the run's bus loads
only softhil's python-can interface (`rigbus.binary`, what `can.Bus(interface="softhil")` loads
through its entry point) and the wire format it speaks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PROBE = """
import importlib, json, pkgutil, sys
import controllers
from rigbus import ccodec
for info in pkgutil.iter_modules(controllers.__path__):
    importlib.import_module(f"controllers.{info.name}")
assert ccodec.load() is not None, ccodec.failure()
from rigbus.protocol import DriveStatus, Protocol
protocol = Protocol()
status = DriveStatus(node=2, piston_position=0.01, p_a=1.5e4, p_b=-2e3, fault=0, counter=7)
assert protocol.decode(protocol.encode(status)) == status
plant = lambda: sorted(m for m in sys.modules if m == "hil" or m.startswith("hil."))
before = plant()
from hil.bus.loopback import LoopbackHub  # the test's own hub, not the controller's import
hub = LoopbackHub(handshake_grace=0.0).start()
loaded = set(sys.modules)
from rigbus.canbus import BusSpec, open_bus
bus = open_bus(BusSpec.parse(f"softhil:{hub.port}"))
bus.shutdown()
hub.stop()
print(json.dumps([before, sorted(set(plant()) - loaded)]))
"""


def test_the_controller_side_imports_nothing_of_the_plant() -> None:
    result = subprocess.run(
        [sys.executable, "-c", PROBE], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr[-2000:]
    before, by_the_bus = json.loads(result.stdout.strip().splitlines()[-1])
    assert before == []
    assert set(by_the_bus) <= {"rigbus.binary"}  # hil, hil.bus, rigbus.wire came with the hub
