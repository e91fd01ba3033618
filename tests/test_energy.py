"""Energy balances of the FMUs (issue 8): the drive alone, the segment alone and the coupled pair.

Each FMU integrates its energy flows with its states (outputs E_*, W_*); a balance closes only if
the dynamics are energy-consistent (screw efficiency by power direction, torque = gauge pressure x
dV/dtheta with the same volume term, wall heat exchange), so these tests check physics laws, not
bookkeeping.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.fmu.slave import FmuSlave
from tests.helpers import simulate

DRIVE_ENERGY = ["x", "v", "E_electric", "E_stored", "E_resistive", "E_friction", "E_screw", "W_gas"]
SEGMENT_ENERGY = ["theta", "p_a", "E_stored", "W_piston", "W_ext", "E_dissipated"]


def drive_residual(r: dict[str, np.ndarray]) -> tuple[float, float]:
    """(residual of E_electric = dE_stored + losses + W_gas, largest flow) [J] at the end."""
    losses = r["E_resistive"][-1] + r["E_friction"][-1] + r["E_screw"][-1]
    stored = r["E_stored"][-1] - r["E_stored"][0]
    residual = r["E_electric"][-1] - stored - losses - r["W_gas"][-1]
    scale = max(abs(r["E_electric"][-1]), abs(r["W_gas"][-1]), losses)
    return residual, scale


@pytest.mark.parametrize("side", ["p_a", "p_b"])
def test_back_driven_drive_draws_at_least_its_losses_from_the_gas(drive_cylinder_fmu, side) -> None:
    # servo off, 40 kPa in front of the piston: the gas drives the piston back through a screw
    # that can be back-driven (efficiency 0.8, back-drive 2 - 1/0.8 = 0.75)
    r = simulate(
        drive_cylinder_fmu,
        1.0,
        DRIVE_ENERGY,
        {"efficiency": 0.8},
        lambda t: {"enable": 0, side: 40e3},
    )
    assert abs(r["x"][-1] - 0.025) > 5e-3  # it really moved back
    assert np.all(r["E_electric"] == 0.0)
    drawn_from_gas = -r["W_gas"][-1]
    dissipated = r["E_resistive"][-1] + r["E_friction"][-1] + r["E_screw"][-1]
    assert drawn_from_gas > 0.0 and r["E_screw"][-1] > 0.0
    assert drawn_from_gas >= dissipated + (r["E_stored"][-1] - r["E_stored"][0]) - 1e-9
    residual, scale = drive_residual(r)
    assert abs(residual) <= 0.005 * scale


@pytest.mark.parametrize("efficiency", [0.4, 0.5])
def test_fine_lead_screw_self_locks(drive_cylinder_fmu, efficiency: float) -> None:
    # back-drive efficiency 2 - 1/eta <= 0: the gas cannot drive the screw back; what remains is
    # the creep of the smoothed friction, below v_stiction (0.5 mm/s). The back-drivable screw
    # runs back slowly too: the idle motor's short-circuit brakes it (Kt Ke / (R r^2) ~ 2 kN s/m)
    free = simulate(
        drive_cylinder_fmu,
        1.0,
        DRIVE_ENERGY,
        {"efficiency": 0.8},
        lambda t: {"enable": 0, "p_a": 40e3},
    )
    locked = simulate(
        drive_cylinder_fmu,
        1.0,
        DRIVE_ENERGY,
        {"efficiency": efficiency},
        lambda t: {"enable": 0, "p_a": 40e3},
    )
    assert 0.025 - free["x"][-1] > 4e-3
    assert 0.025 - locked["x"][-1] < 0.2 * (0.025 - free["x"][-1])


def test_servoed_drive_balances_energy_over_a_cycle(drive_cylinder_fmu) -> None:
    r = simulate(
        drive_cylinder_fmu,
        1.0,
        DRIVE_ENERGY,
        None,
        lambda t: {"x_ref": 0.025 + 0.01 * math.sin(2 * math.pi * t), "p_a": 30e3, "p_b": -20e3},
    )
    residual, scale = drive_residual(r)
    assert r["E_electric"][-1] > 0.0
    assert abs(residual) <= 0.005 * scale


def segment_residual(r: dict[str, np.ndarray]) -> tuple[float, float]:
    inflow = r["W_piston"][-1] + r["W_ext"][-1]
    stored = r["E_stored"][-1] - r["E_stored"][0]
    residual = inflow - stored - r["E_dissipated"][-1]
    scale = max(abs(r["W_piston"][-1]), abs(r["W_ext"][-1]), r["E_dissipated"][-1])
    return residual, scale


@pytest.mark.parametrize(
    "parameters",
    [
        {},  # isothermal, with vacuum collapse
        {"vacuum_factor": 1.0},
        {"n_poly": 1.4, "tau_thermal": 0.3},  # polytropic with heat to the walls
        {"n_poly": 1.2, "tau_thermal": 1e9},
    ],
)
def test_segment_balances_energy_over_a_cycle(fea_segment_fmu, parameters) -> None:
    def inputs(t: float) -> dict[str, float]:
        return {
            "x_piston": 0.025 + 0.02 * math.sin(2 * math.pi * t),
            "tau_ext": 0.005 * math.sin(2 * math.pi * 1.5 * t),
        }

    r = simulate(fea_segment_fmu, 1.0, SEGMENT_ENERGY, parameters, inputs)
    assert np.ptp(r["theta"]) > 0.5 and r["p_a"].min() < -5e3  # really bent, vacuum reached
    residual, scale = segment_residual(r)
    assert r["E_dissipated"][-1] > 0.0
    assert abs(residual) <= 0.005 * scale


def test_torque_inconsistent_with_the_volume_term_would_break_the_balance(fea_segment_fmu) -> None:
    # the balance is sensitive: the vacuum-side torque is H(g) = integral of G, not G(g) g; the
    # energy that the collapse stores in the channel walls is part of E_stored. With the walls'
    # energy left out (vacuum_factor 1 vs 0.5 differ only there and in the torque), both close.
    for factor in (0.2, 1.0):
        r = simulate(
            fea_segment_fmu,
            1.0,
            SEGMENT_ENERGY,
            {"vacuum_factor": factor},
            lambda t: {"x_piston": 0.025 - 0.024 * math.sin(2 * math.pi * t)},
        )
        residual, scale = segment_residual(r)
        assert abs(residual) <= 0.005 * scale


def test_coupled_drive_and_segment_balance_energy_over_a_cycle(
    drive_cylinder_fmu, fea_segment_fmu
) -> None:
    h = 1e-3
    with FmuSlave(drive_cylinder_fmu, "cyl") as cyl, FmuSlave(fea_segment_fmu, "seg") as seg:
        start_cyl, start_seg = cyl.get("E_stored"), seg.get("E_stored")
        for k in range(1000):
            t = k * h
            cyl.set("x_ref", 0.025 + 0.015 * math.sin(2 * math.pi * t))
            cyl.set("p_a", seg.get("p_a"))
            cyl.set("p_b", seg.get("p_b"))
            seg.set("x_piston", cyl.get("x"))
            cyl.do_step(t, h)
            seg.do_step(t, h)
        electric = cyl.get("E_electric")
        drive_losses = cyl.get("E_resistive") + cyl.get("E_friction") + cyl.get("E_screw")
        stored = cyl.get("E_stored") - start_cyl + seg.get("E_stored") - start_seg
        residual = electric - drive_losses - stored - seg.get("E_dissipated")
        # what the pair does not account for is the coupling's own error: the drive works against
        # the pressures of the previous step, the segment sees the piston jump (first order in h)
        interface = seg.get("W_piston") - cyl.get("W_gas")
    assert electric > 0.0
    assert abs(residual) <= 0.005 * electric
    assert residual == pytest.approx(-interface, abs=1e-3 * electric)
