"""The drive servo's design on the firmware's true structure, checked against the FMU (issue 8.2).

The firmware differentiates the measurement, so the reference-to-position response is
(Kp + Ki/s) G / (1 + C G); the design's bandwidth is computed on that, and the FMU's measured
small-signal response (a sine sweep through fmpy) must match it.
"""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

import fmus
from controllers.servo_design import (
    DrivePlant,
    ServoGains,
    ServoSpec,
    analyse,
    closed_loop_bandwidth_hz,
    reference_response,
)
from tests.helpers import simulate

TOML = fmus.source_root() / "DriveCylinder" / "model.toml"


def default_gains() -> ServoGains:
    params = tomllib.loads(TOML.read_text())["parameters"]
    return ServoGains(*(float(params[k]["start"]) for k in ("Kp", "Ki", "Kd", "Tf")))


def test_bandwidth_is_computed_on_the_derivative_on_measurement_structure() -> None:
    plant = DrivePlant.from_model_toml(TOML)
    # the gains designed as if D acted on the error: their true bandwidth is about 4.6 Hz
    old = ServoGains(Kp=36000.0, Ki=120000.0, Kd=1300.0, Tf=3.7e-3)
    assert closed_loop_bandwidth_hz(plant, old) == pytest.approx(4.6, abs=0.3)
    assert not analyse(plant, old).meets(ServoSpec())
    design = analyse(plant, default_gains())
    assert design.meets(ServoSpec())
    assert design.bandwidth_hz >= 10.0 and design.phase_margin_deg >= 45.0


def measured_gain(fmu, frequency: float, amplitude: float = 2e-4) -> complex:
    """Complex x / x_ref of the FMU at one frequency: a lock-in over whole periods after the
    transient."""
    duration = 1.0 + 4.0 / frequency
    r = simulate(
        fmu,
        duration,
        ["x"],
        None,
        lambda t: {"x_ref": 0.025 + amplitude * math.sin(2 * math.pi * frequency * t)},
    )
    # the firmware samples x(t_k) and x_ref(t_k) together, as the design's T(z) relates them
    t_in = r["time"][:-1]
    x_out = r["x"][:-1] - 0.025
    settled = t_in >= duration - 4.0 / frequency - 1e-9
    phase = np.exp(-1j * 2 * math.pi * frequency * t_in[settled])
    response = np.mean(x_out[settled] * phase)
    excitation = np.mean(amplitude * np.sin(2 * math.pi * frequency * t_in[settled]) * phase)
    return complex(response / excitation)


@pytest.mark.parametrize("frequency", [2.0, 5.0, 10.0, 14.0])
def test_fmu_small_signal_response_matches_the_design(drive_cylinder_fmu, frequency) -> None:
    plant = DrivePlant.from_model_toml(TOML)
    designed = complex(reference_response(plant, default_gains(), np.array([frequency]))[0])
    measured = measured_gain(drive_cylinder_fmu, frequency)
    # Coulomb friction and the sampled output make the FMU differ a little from the linear design
    assert abs(measured) == pytest.approx(abs(designed), rel=0.1)
    assert abs(measured - designed) < 0.15 * abs(designed)
    if frequency <= 10.0:
        assert abs(measured) > 1 / math.sqrt(2)  # inside the >= 10 Hz small-signal bandwidth
