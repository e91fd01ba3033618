"""DriveCylinder physics and servo (fmus/DriveCylinder/model.c), simulated through fmpy."""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import numpy as np
import pytest

import fmus
from controllers.servo_design import DrivePlant, ServoGains, ServoSpec, analyse
from hil.errors import FmuError
from hil.fmu.slave import FmuSlave
from tests.helpers import simulate

STROKE = 0.05
MID = 0.025
OUTPUTS = ["x", "v", "i_motor", "u_motor", "fault"]


def test_default_servo_gains_meet_the_design_specification() -> None:
    toml = fmus.source_root() / "DriveCylinder" / "model.toml"
    import tomllib

    params = tomllib.loads(toml.read_text())["parameters"]
    gains = ServoGains(*(params[k]["start"] for k in ("Kp", "Ki", "Kd", "Tf")))
    spec = ServoSpec()
    design = analyse(DrivePlant.from_model_toml(toml), gains, spec)
    assert design.phase_margin_deg >= 45.0
    assert design.bandwidth_hz >= 10.0
    assert design.meets(spec)


def test_servo_follows_a_10mm_step_within_the_designed_time(drive_cylinder_fmu) -> None:
    spec = ServoSpec()
    target = MID + spec.step
    r = simulate(drive_cylinder_fmu, 1.0, OUTPUTS, inputs=lambda t: {"x_ref": target})
    x, t = r["x"], r["time"]
    assert np.all(x <= STROKE) and np.all(x >= 0.0)
    overshoot = (x.max() - target) / spec.step
    assert overshoot < 0.10
    outside = np.nonzero(np.abs(x - target) > 0.02 * spec.step)[0]
    settling = t[outside[-1] + 1]
    assert settling <= spec.settling_time
    assert abs(x[-1] - target) < 0.02 * spec.step
    # the move is voltage-limited: the servo saturates at the supply and never beyond it
    assert np.max(np.abs(r["u_motor"])) == pytest.approx(12.0)


def test_end_stops_hold_under_a_large_setpoint(drive_cylinder_fmu) -> None:
    for x_ref, stop in [(1.0, STROKE), (-1.0, 0.0)]:
        r = simulate(
            drive_cylinder_fmu, 1.5, OUTPUTS, inputs=lambda t, x_ref=x_ref: {"x_ref": x_ref}
        )
        x = r["x"]
        assert np.all(x <= STROKE) and np.all(x >= 0.0)
        assert x[-1] == stop
        assert abs(r["v"][-1]) == 0.0
        fault = int(r["fault"][-1])
        assert fault & 1 and fault & 2  # end stop contact, setpoint clamped


def test_servo_holds_position_against_chamber_pressure(drive_cylinder_fmu) -> None:
    # 40 kPa in front of the piston pushes it back with 20 N; integral action removes the offset
    r = simulate(
        drive_cylinder_fmu,
        3.0,
        OUTPUTS,
        inputs=lambda t: {"x_ref": 0.030, "p_a": 40e3, "p_b": 0.0},
    )
    assert abs(r["x"][-1] - 0.030) < 2e-5
    # the motor now carries the load: at rest the screw's friction holds any motor torque between
    # the back-driving r eta_b F and the driving r F / eta, so the current lies in that band
    force = 40e3 * np.pi * 0.0254**2 / 4
    r_screw, eta = 1e-3 / (2 * np.pi), 0.5
    band = (r_screw * force * (2 - 1 / eta) / 0.0382, r_screw * force / eta / 0.0382)
    assert band[0] - 1e-3 <= r["i_motor"][-1] <= band[1] + 1e-3
    assert r["i_motor"][-1] > 0.1 * band[1]  # and it really pushes


def test_disabled_servo_applies_no_voltage(drive_cylinder_fmu) -> None:
    r = simulate(drive_cylinder_fmu, 0.3, OUTPUTS, inputs=lambda t: {"x_ref": 0.04, "enable": 0})
    assert np.all(r["u_motor"] == 0.0)
    assert np.all(r["x"] == MID)


def test_stall_fault_when_blocked_by_pressure(drive_cylinder_fmu) -> None:
    # 250 kPa on 507 mm^2 is 127 N, more than the 50 N the motor can push: it stalls
    r = simulate(drive_cylinder_fmu, 1.5, OUTPUTS, inputs=lambda t: {"x_ref": 0.04, "p_a": 250e3})
    assert int(r["fault"][-1]) & 4
    assert r["x"][-1] < MID + 1e-3


@pytest.mark.parametrize(
    ("parameters", "message"),
    [
        ({"stroke": -0.05}, "invalid parameter stroke = -0.05"),
        ({"efficiency": 0.0}, "invalid parameter efficiency"),
        ({"x_start": 0.08}, "invalid parameter x_start = 0.08: outside the stroke"),
        ({"substep": 5e-3}, "invalid parameter substep"),
    ],
)
def test_invalid_parameter_fails_initialisation_with_a_message(
    drive_cylinder_fmu, parameters: dict[str, float], message: str
) -> None:
    with pytest.raises(FmuError, match="fmi2ExitInitializationMode failed") as info:
        FmuSlave(drive_cylinder_fmu, "cyl", parameters)
    assert message in str(info.value)


def test_non_finite_input_is_an_error(drive_cylinder_fmu) -> None:
    with FmuSlave(drive_cylinder_fmu, "cyl") as slave:
        with pytest.raises(FmuError, match="non-finite value for p_a"):
            slave.set("p_a", float("inf"))
        with pytest.raises(FmuError, match="x is an output and cannot be set"):
            slave.set("x", 0.01)
        with pytest.raises(FmuError, match="parameter stroke is fixed after initialisation"):
            slave.set("stroke", 0.01)


def test_substep_beyond_the_stated_stability_limit_is_rejected(drive_cylinder_fmu) -> None:
    # a slipperier seal (smaller v_stiction) stiffens the mechanics: the limit moves below 1 ms
    with pytest.raises(FmuError, match="beyond the stability limit") as info:
        FmuSlave(drive_cylinder_fmu, "cyl", {"v_stiction": 1e-5, "substep": 5e-4})
    assert "substep = 0.0005" in str(info.value)
    # the electrical pole (R/L = 1e4 1/s) no longer limits: a stiffer one is integrated exactly
    r = simulate(drive_cylinder_fmu, 0.5, OUTPUTS, {"L_motor": 1e-5}, lambda t: {"x_ref": 0.03})
    assert np.all(np.isfinite(r["x"])) and abs(r["x"][-1] - 0.03) < 1e-4


def test_stated_stability_limit_is_the_friction_slopes(drive_cylinder_fmu) -> None:
    """The limit the model states is RK4's 2.5 / lambda for the friction's slope at rest
    (the smoothstep's 35/32 / v_stiction times the seal's Coulomb force plus the screw's at the
    motor's stall force), reflected through the screw: derived here from the parameters."""
    p = {
        name: drive_cylinder_fmu.spec.variable(name).start
        for name in ("lead", "J", "F_coulomb", "efficiency", "Kt", "u_max", "R_motor")
    }
    v_stiction = 1e-4
    r = p["lead"] / (2 * math.pi)
    stall = p["Kt"] * p["u_max"] / (p["R_motor"] * r)
    slope = 35 / 32 * (p["F_coulomb"] + (1 / p["efficiency"] - 1) * stall) / v_stiction
    expected = 2.5 * p["J"] / (r * r * slope)
    with pytest.raises(FmuError, match="beyond the stability limit") as info:
        FmuSlave(drive_cylinder_fmu, "cyl", {"v_stiction": v_stiction})
    stated = float(re.search(r"stability limit ([0-9.e+-]+) s", str(info.value)).group(1))
    assert stated == pytest.approx(expected, rel=1e-5)


def test_stated_stability_limit_holds_under_load(drive_cylinder_fmu) -> None:
    # just inside the stated limit (friction stiffened 5x) a loaded servo move stays finite and
    # agrees with an 8x finer reference (measured 1e-6 of the stroke's range, 2e-6 of the current's)
    with pytest.raises(FmuError, match="beyond the stability limit") as info:
        FmuSlave(drive_cylinder_fmu, "cyl", {"v_stiction": 1e-4})
    limit = float(re.search(r"stability limit ([0-9.e+-]+) s", str(info.value)).group(1))

    def move(t: float) -> dict[str, float]:
        return {"x_ref": 0.025 + 0.01 * math.sin(2 * math.pi * t), "p_a": 30e3, "p_b": -20e3}

    outputs = ["x", "i_motor"]
    near = simulate(
        drive_cylinder_fmu, 0.5, outputs, {"v_stiction": 1e-4, "substep": 0.95 * limit}, move
    )
    fine = simulate(
        drive_cylinder_fmu, 0.5, outputs, {"v_stiction": 1e-4, "substep": limit / 8}, move
    )
    for name in outputs:
        assert np.max(np.abs(near[name] - fine[name])) < 1e-5 * np.ptp(fine[name]), name


def assert_agrees_with_finer_substeps(
    fmu,  # noqa: ANN001 - the BuiltFmu fixture
    duration: float,
    inputs: Callable[[float], dict[str, float]],
    finer: int,
    tolerance: float,
    parameters: dict[str, float] | None = None,
) -> None:
    """Position, speed and current with the default substep within `tolerance` of each signal's
    range of the same run with `finer` times shorter substeps."""
    outputs = ["x", "v", "i_motor"]
    substep = fmu.spec.variable("substep").start / finer
    coarse = simulate(fmu, duration, outputs, parameters, inputs)
    fine = simulate(fmu, duration, outputs, {**(parameters or {}), "substep": substep}, inputs)
    for name in outputs:
        span = np.ptp(fine[name])
        assert np.max(np.abs(coarse[name] - fine[name])) < tolerance * span, name


def test_servo_move_converges_with_the_substep(drive_cylinder_fmu) -> None:
    # the default substep (set by the mechanics, the electrical pole exact, the friction's band
    # split finer) against a 4x finer reference over a servo move with chamber load and two
    # reversals: every signal within 1e-6 of its range (measured x 5e-9, v 6e-8, i 1.4e-7)
    def move(t: float) -> dict[str, float]:
        return {"x_ref": 0.025 + 0.01 * math.sin(2 * math.pi * t), "p_a": 20e3, "p_b": -15e3}

    assert_agrees_with_finer_substeps(drive_cylinder_fmu, 1.0, move, 4, 1e-6)


def test_starts_from_rest_converge_with_the_substep(drive_cylinder_fmu) -> None:
    """What the closed loop does to a drive: setpoint steps every 0.2 s from rest, held in
    between against chamber pressures that change with them. A servo sample that changes the
    voltage starts the piston within the substep that follows, through the friction's band at
    the acceleration the new voltage gives; against a 4x finer reference every signal agrees
    within 1e-6 of its range (measured x 4e-9, v 6e-8, i 2.5e-7; 2.4e-5 for the current if the
    band is split by the acceleration before the voltage acts)."""
    steps = [0.025, 0.03, 0.0305, 0.022, 0.0221, 0.035, 0.034, 0.02]

    def hold(t: float) -> dict[str, float]:
        k = min(int(t / 0.2), len(steps) - 1)
        dp = 4e5 * (steps[k] - 0.025)  # the bent segment's pressure difference
        return {"x_ref": steps[k], "p_a": dp / 2, "p_b": -dp / 2}

    assert_agrees_with_finer_substeps(drive_cylinder_fmu, 1.6, hold, 4, 1e-6)


def test_linear_drive_is_integrated_exactly_whatever_the_substep(drive_cylinder_fmu) -> None:
    """Without Coulomb seal friction and with a lossless screw the drive is linear between servo
    samples (held voltage, constant chamber load): the solver's exact block leaves nothing to
    the explicit part, so the default substep agrees with a 16x finer one to rounding, not to
    the method's order (the same move with friction differs by 1.4e-7 of the current's range)."""
    linear = {"F_coulomb": 0.0, "efficiency": 1.0}

    def move(t: float) -> dict[str, float]:
        return {"x_ref": 0.025 + 0.01 * math.sin(2 * math.pi * t), "p_a": 20e3, "p_b": -15e3}

    assert_agrees_with_finer_substeps(drive_cylinder_fmu, 1.0, move, 16, 1e-9, linear)


def test_substeps_of_changing_length_integrate_as_accurately_as_equal_ones(
    drive_cylinder_fmu,
) -> None:
    """A servo period that does not divide the step splits every step into substeps of varying
    length: the solver's cached exponential coefficients must follow the length (a stale cache
    integrates the electrical pole with the wrong exponential). Against a 4x finer reference
    the current agrees as closely as with equal substeps."""
    parameters = {"servo_period": 7e-4, "p_a": 2e4}
    outputs = ["i_motor", "x"]
    got = simulate(drive_cylinder_fmu, 0.2, outputs, parameters, lambda t: {"x_ref": 0.03})
    fine = simulate(
        drive_cylinder_fmu,
        0.2,
        outputs,
        {**parameters, "substep": 5e-4 / 4},
        lambda t: {"x_ref": 0.03},
    )
    span = np.ptp(fine["i_motor"])
    assert span > 0.1  # the servo drives the motor hard: the pole is exercised
    assert np.max(np.abs(got["i_motor"] - fine["i_motor"])) < 1e-3 * span
