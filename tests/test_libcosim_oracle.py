"""Our FMUs and our master against an independent master: libcosim (through libcosimpy).

The DriveCylinder and FeaSegment FMUs, coupled the same way (piston position to the segment,
chamber pressures back to the cylinder), are stepped at 1 ms by libcosim's fixed-step algorithm
and by `hil.cosim.Algorithm`. Both are Jacobi-type fixed-step masters with integer time, so the
trajectories must agree to rounding. (This test found that the FMUs did not compute their outputs
in initialisation mode, where libcosim propagates start values through the connections.)
libcosim is run in a subprocess pinned to one core, as libcosimpy requires here.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from hil.cosim import Algorithm, Connection, FmuParticipant
from hil.fmu.build import build_fmu
from hil.fmu.slave import FmuSlave

SAMPLES, EVERY = 30, 50  # 30 samples, one every 50 ms, over 1.5 s

LIBCOSIM_SCRIPT = """
import json, sys
from libcosimpy.CosimExecution import CosimExecution
from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
from libcosimpy.CosimObserver import CosimObserver
from libcosimpy.CosimSlave import CosimLocalSlave
log_output_level(CosimLogLevel.ERROR)
args = json.loads(sys.argv[1])
ex = CosimExecution.from_step_size(step_size=1_000_000)
cyl = ex.add_local_slave(CosimLocalSlave(fmu_path=args["cylinder"], instance_name="cylinder1"))
seg = ex.add_local_slave(CosimLocalSlave(fmu_path=args["segment"], instance_name="segment1"))
vr = args["vr"]
ex.connect_real_variables(cyl, vr["x"], seg, vr["x_piston"])
ex.connect_real_variables(seg, vr["p_a"], cyl, vr["cyl_p_a"])
ex.connect_real_variables(seg, vr["p_b"], cyl, vr["cyl_p_b"])
ex.real_initial_value(cyl, vr["x_ref"], 0.040)
observer = CosimObserver.create_last_value()
ex.add_observer(observer)
rows = []
for k in range(1, args["samples"] + 1):
    ex.simulate_until(k * args["every"] * 1_000_000)
    rows.append(observer.last_real_values(cyl, [vr["x"]]) +
                observer.last_real_values(seg, [vr["kappa"], vr["p_a"]]))
print(json.dumps(rows))
"""


def test_libcosim_and_our_master_agree_on_the_coupled_fmus() -> None:
    cylinder, segment = build_fmu("DriveCylinder"), build_fmu("FeaSegment")
    c, s = cylinder.spec.variable, segment.spec.variable
    vr = {
        "x": c("x").value_reference,
        "x_ref": c("x_ref").value_reference,
        "cyl_p_a": c("p_a").value_reference,
        "cyl_p_b": c("p_b").value_reference,
        "x_piston": s("x_piston").value_reference,
        "kappa": s("kappa").value_reference,
        "p_a": s("p_a").value_reference,
        "p_b": s("p_b").value_reference,
    }
    args = {
        "cylinder": str(cylinder.path),
        "segment": str(segment.path),
        "vr": vr,
        "samples": SAMPLES,
        "every": EVERY,
    }
    result = subprocess.run(
        ["taskset", "-c", "0", sys.executable, "-c", LIBCOSIM_SCRIPT, json.dumps(args)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    theirs = np.array(json.loads(result.stdout.strip().splitlines()[-1]))

    participants = [
        FmuParticipant(FmuSlave(cylinder, "cylinder1", {"x_ref": 0.040})),
        FmuParticipant(FmuSlave(segment, "segment1")),
    ]
    master = Algorithm(
        participants,
        [
            Connection("cylinder1.x", "segment1.x_piston"),
            Connection("segment1.p_a", "cylinder1.p_a"),
            Connection("segment1.p_b", "cylinder1.p_b"),
        ],
        1e-3,
    )
    ours = []
    for k in range(1, SAMPLES + 1):
        master.advance_to(k * EVERY)
        ours.append(
            [
                master.values["cylinder1.x"],
                master.values["segment1.kappa"],
                master.values["segment1.p_a"],
            ]
        )
    for p in participants:
        p.close()
    ours_array = np.array(ours)
    # the step really moved the arm: 15 mm of piston, a bend of ~12 1/m, ~15 kPa
    assert ours_array[-1, 0] > 0.039 and ours_array[-1, 1] > 10.0 and ours_array[-1, 2] > 10e3
    scale = np.max(np.abs(ours_array), axis=0)
    assert np.max(np.abs(theirs - ours_array) / scale) < 1e-12
