"""Design of the outer curvature PI for the selected estimator's effective delay (python-control).

The segment is the first-order lag of `controllers.curvature.SegmentModel`,
    G(s) = K / (tau s + 1)   (kappa per piston position),
the PI cancels its pole, C(s) = Kp (1 + 1 / (tau s)), Kp = wc tau / K, so the loop is
    L(s) = (wc / s) e^{-s D}
with D the effective delay: half a control period for the zero-order hold of the setpoint, one
control period of computation (the command computed at SYNC c acts from SYNC c + 1), and the age
of the estimate (`estimator_delay`). Its phase margin is 90 deg - wc D, so the crossover for a
phase margin target is wc = (pi/2 - PM) / D, capped at `max_crossover_hz`. Margins are computed
on L with D as a Pade approximant. The drive's inner position servo (>= 10 Hz closed-loop
bandwidth, controllers.servo_design.ServoSpec) is left out: its lag adds to D at the crossovers
used here.

The gains are closed-form (`outer_loop_gains`, what every run needs); python-control, which takes
1-2 s to import, is imported only where margins are measured (`design_outer_loop`, `hil tune`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from controllers.curvature import ArmGains, PiGains, SegmentModel

if TYPE_CHECKING:
    import control


# the inertial part's closed-loop pole per crossover (`arm_loop_gains`): at a half the drive
# follows the six-segment arm's moves; at the crossover itself its pistons swing against their
# ends on a 0.3 m move (measured)
POLE_SHARE = 0.5


def estimator_delay(name: str, control_period: float, latency_compensation: bool = True) -> float:
    """Age of the estimate at the SYNC [s].

    The frame used at SYNC c was exposed at (c - 1) T. `raw` reports it as it is (age T); `kf`
    and `ukf` with latency compensation carry it to the SYNC with the recorded pressures (age 0:
    the model's response to the measured input has no lag, only the unmodelled torque's share
    is late); without compensation they are one period late again.

    Parameters
    ----------
    name
        "raw", "kf" or "ukf".
    control_period
        T [s].
    latency_compensation
        Whether the filter fuses at the exposure time.
    """
    if name == "raw":
        return control_period
    if name in ("kf", "ukf"):
        return 0.0 if latency_compensation else control_period
    raise ValueError(f"unknown estimator {name!r}: choose one of raw, kf, ukf")


@dataclass(frozen=True)
class LoopDesign:
    """A designed outer loop: gains, crossover [Hz], gain margin (ratio, inf if none), phase
    margin [deg] and the effective delay D [s] it was designed for."""

    gains: PiGains
    crossover_hz: float
    gain_margin: float
    phase_margin_deg: float
    delay: float


def effective_delay(estimator_age: float, control_period: float) -> float:
    """D [s]: zero-order hold (T/2), computation (T) and the estimate's age."""
    return 1.5 * control_period + estimator_age


def loop_transfer(
    model: SegmentModel, gains: PiGains, delay: float, pade_order: int = 5
) -> control.TransferFunction:
    """Open loop C(s) G(s) e^{-s D} with the delay as a Pade approximant."""
    import control

    K, tau = model.static_gain(), model.time_constant()
    plant = control.tf([K], [tau, 1.0])
    pi = control.tf([gains.Kp, gains.Ki], [1.0, 0.0])
    num, den = control.pade(delay, pade_order) if delay > 0.0 else ([1.0], [1.0])
    return pi * plant * control.tf(num, den)


def outer_loop_gains(
    model: SegmentModel,
    delay: float,
    phase_margin_deg: float = 60.0,
    max_crossover_hz: float = 2.0,
) -> PiGains:
    """Pole-cancelling PI whose crossover gives `phase_margin_deg` with the effective delay
    `delay` [s], no faster than `max_crossover_hz` (see `curvature.design_pi`)."""
    if not 0.0 < phase_margin_deg < 90.0:
        raise ValueError(f"phase_margin_deg: must be within (0, 90), got {phase_margin_deg}")
    wc_cap = 2.0 * math.pi * max_crossover_hz
    wc = wc_cap if delay <= 0.0 else min(wc_cap, math.radians(90.0 - phase_margin_deg) / delay)
    tau = model.time_constant()
    Kp = wc * tau / model.static_gain()
    return PiGains(Kp=Kp, Ki=Kp / tau)


def arm_loop_gains(
    models: Sequence[SegmentModel],
    masses: Sequence[float],
    delay: float,
    phase_margin_deg: float = 60.0,
    max_crossover_hz: float = 2.0,
) -> ArmGains:
    """The curvature loops of a multibody arm whose mass matrix M(q) couples its bends
    (`controllers.curvature.ArmGains`): `M theta'' + D theta' + K theta = T x` (D, K the bends'
    damping and bending plus gas stiffness, T the torque per piston travel, all diagonal). Each
    bend alone has its pole at k / d and the PI of `outer_loop_gains` cancels it; here the base
    carries the whole outer arm (M_11 = 6e-3 kg m^2 on the straight six-segment planar arm,
    M / d ~ 1 s), the arm's first mode is lightly damped (0.26 Hz, zeta 0.16), and those PIs,
    one per segment, make it unstable (a mode growing at 0.7 1/s, linearised below).

    The design, in torque per piston:
        T x = (3 p^2 M + wc D) e + (wc K + p^3 M) integral(e) - 3 p M theta' + feedforward,
    wc the crossover of `outer_loop_gains`, p = POLE_SHARE wc. Without inertia it is that
    per-segment PI exactly (Kp = wc tau / K, Ki = Kp / tau); the inertial terms put every mode
    of M e'' + ... on a triple pole at -p (M s^3 + 3 p M s^2 + 3 p^2 M s + p^3 M), the damping
    and stiffness shared out by the mass matrix, so that the light tip modes get no more than
    the loop's delay allows. M is the arm's at the estimated configuration: curled, the base
    carries a third of the straight arm's (0.34 at -12..-16 1/m), and gains designed on the
    straight arm oscillate there. On a planned move the references' rate and acceleration are
    fed forward through D + 3 p M and M (the inverse dynamics; the derivative term on the
    measured rate would brake the move). Measured on the six-segment planar arm (linearised,
    10 ms period, 16 ms drive lag, state known, 1 Hz, p = 3.1 1/s): every closed-loop pole
    damped at zeta >= 0.67, the slowest decaying at 2.1 1/s (0.67-0.72 with the plant's M 40 %
    under or 30 % over the design's); a mass-proportional damping injection under the
    per-segment PI instead left modes at zeta 0.3 decaying at 0.5 1/s."""
    wc_cap = 2.0 * math.pi * max_crossover_hz
    wc = wc_cap if delay <= 0.0 else min(wc_cap, math.radians(90.0 - phase_margin_deg) / delay)
    stiffness = [m.k_bend + m.gas_stiffness() for m in models]
    return ArmGains(
        crossover=wc,
        pole=POLE_SHARE * wc,
        lengths=tuple(m.length for m in models),
        masses=tuple(float(v) for v in masses),
        torque=tuple(
            m.static_gain() * m.length * k for m, k in zip(models, stiffness, strict=True)
        ),
        damping=tuple(m.d_bend for m in models),
        stiffness=tuple(stiffness),
    )


def design_outer_loop(
    model: SegmentModel,
    delay: float,
    phase_margin_deg: float = 60.0,
    max_crossover_hz: float = 2.0,
    pade_order: int = 5,
) -> LoopDesign:
    """`outer_loop_gains` with its margins measured on the Pade loop."""
    import control

    gains = outer_loop_gains(model, delay, phase_margin_deg, max_crossover_hz)
    gm, pm, _, wpc = control.margin(loop_transfer(model, gains, delay, pade_order))
    return LoopDesign(gains, float(wpc) / (2.0 * math.pi), float(gm), float(pm), delay)


def write_bode_png(
    model: SegmentModel, design: LoopDesign, path: Path, pade_order: int = 5
) -> None:
    """Bode plot of the designed open loop to `path` (PNG), with the crossover and margins."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    loop = loop_transfer(model, design.gains, design.delay, pade_order)
    omega = np.logspace(-1, 3, 400)
    response = loop(1j * omega)
    magnitude = 20.0 * np.log10(np.abs(response))
    phase = np.degrees(np.unwrap(np.angle(response)))
    hz = omega / (2.0 * math.pi)
    figure, (top, bottom) = plt.subplots(2, 1, sharex=True, figsize=(7, 6))
    top.semilogx(hz, magnitude)
    top.axhline(0.0, color="grey", lw=0.8)
    top.set_ylabel("|L| [dB]")
    top.set_title(
        f"outer curvature loop: crossover {design.crossover_hz:.2f} Hz, "
        f"PM {design.phase_margin_deg:.0f} deg, delay {1e3 * design.delay:.0f} ms"
    )
    bottom.semilogx(hz, phase)
    bottom.axhline(-180.0, color="grey", lw=0.8)
    bottom.set_ylabel("phase [deg]")
    bottom.set_xlabel("frequency [Hz]")
    for axis in (top, bottom):
        axis.axvline(design.crossover_hz, color="tab:red", lw=0.8, ls="--")
        axis.grid(True, which="both", alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
