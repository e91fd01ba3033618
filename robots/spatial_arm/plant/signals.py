"""What the spatial arm records (one column per quantity per segment or drive), plots, and puts
on the bus (for the bus load)."""

from __future__ import annotations

from hil.devices import HEARTBEAT_PERIOD
from hil.rig import PlotSpec, SignalSpec

PER_SEGMENT: tuple[tuple[str, str, str, str], ...] = (
    ("theta_x", "rad", "true bend towards +x", "body.theta_x_{i}"),
    ("theta_y", "rad", "true bend towards +y", "body.theta_y_{i}"),
    ("tip_x", "m", "endplate x (base frame)", "body.tip_x_{i}"),
    ("tip_y", "m", "endplate y", "body.tip_y_{i}"),
    ("tip_z", "m", "endplate z", "body.tip_z_{i}"),
)
PER_DRIVE: tuple[tuple[str, str, str, str], ...] = (
    ("p_a", "Pa", "gauge pressure of side a", "body.p_a_{axis}_{i}"),
    ("p_b", "Pa", "gauge pressure of side b", "body.p_b_{axis}_{i}"),
    ("x", "m", "piston position", "cylinder{n}.x"),
    ("x_ref", "m", "piston setpoint the drive firmware applies", "drive{n}.x_ref"),
    ("i_motor", "A", "drive motor current", "cylinder{n}.i_motor"),
    ("fault", "", "drive fault bits (DriveStatus.fault)", "drive{n}.fault"),
)
ENERGY: tuple[tuple[str, str], ...] = (
    ("E_kinetic", "kinetic energy of the arm"),
    ("E_gravity", "gravitational energy (zero at the base)"),
    ("E_elastic", "bending energy"),
    ("E_gas", "energy stored in the gas circuits"),
    ("E_dissipated", "energy dissipated by bending damping since the start"),
    ("W_piston", "work of the pistons on the gas since the start"),
)
TASK_SIGNALS: tuple[tuple[str, str, str], ...] = (
    ("target_index", "", "goal pursued, 0 first (modulo 256)"),
    ("phase", "", "task phase: 0 idle, 1 moving, 2 settling, 3 settled, 4 done"),
    ("target_x", "m", "task-space reference point x, as the controller reported it"),
    ("target_y", "m", "task-space reference point y, as the controller reported it"),
    ("target_z", "m", "task-space reference point z, as the controller reported it"),
)


def axis_of(n: int) -> tuple[int, str]:
    """(segment, axis) of drive `n`: drive 2i - 1 is segment i's x pair, 2i its y pair."""
    return (n + 1) // 2, "x" if n % 2 else "y"


def signals(segments: int) -> list[SignalSpec]:
    specs: list[SignalSpec] = []
    for i in range(1, segments + 1):
        for name, unit, text, source in PER_SEGMENT:
            specs.append(
                SignalSpec(f"{name}_{i}", unit, f"segment {i}: {text}", source=source.format(i=i))
            )
    for n in range(1, 2 * segments + 1):
        i, axis = axis_of(n)
        where = f"drive {n} (segment {i}, {axis} pair)"
        for name, unit, text, source in PER_DRIVE:
            specs.append(
                SignalSpec(
                    f"{name}_{n}",
                    unit,
                    f"{where}: {text}",
                    source=source.format(n=n, i=i, axis=axis),
                )
            )
        for name, text in (
            ("kappa_ref", "bend curvature reference (theta / L), as the controller reported it"),
            ("kappa_est", "controller's bend curvature estimate, as it reported it"),
        ):
            specs.append(
                SignalSpec(
                    f"{name}_{n}", "1/m", f"{where}: {text}", frame=("ControllerState", n, name)
                )
            )
    for name, text in ENERGY:
        specs.append(SignalSpec(name, "J", text, source=f"body.{name}"))
    for name, unit, text in TASK_SIGNALS:
        specs.append(SignalSpec(name, unit, text, frame=("SpatialTaskState", None, name)))
    return specs


def plots(segments: int) -> list[PlotSpec]:
    drives = tuple(
        f"segment {axis_of(n)[0]}, {axis_of(n)[1]} pair (drive {n})"
        for n in range(1, 2 * segments + 1)
    )
    return [
        PlotSpec(
            "curvature",
            "bend curvature [1/m]",
            drives,
            (
                ("kappa_ref_{n}", "reference", 1.0, {"color": "black", "linestyle": "--"}),
                ("kappa_est_{n}", "estimate (controller)", 1.0, {"color": "tab:orange"}),
            ),
        ),
        PlotSpec(
            "pressures",
            "gauge pressure [kPa]",
            drives,
            (
                ("p_a_{n}", "side a", 1e-3, {"color": "tab:red"}),
                ("p_b_{n}", "side b", 1e-3, {"color": "tab:green"}),
            ),
        ),
        PlotSpec(
            "piston",
            "piston [mm]",
            drives,
            (
                ("x_ref_{n}", "setpoint", 1e3, {"color": "black", "linestyle": "--"}),
                ("x_{n}", "position", 1e3, {"color": "tab:purple"}),
            ),
        ),
    ]


def frame_rates(
    drives: int, markers: int, control_period: float, camera_rate: float
) -> dict[str, float]:
    per_period = 1.0 / control_period
    rates: dict[str, float] = {"SYNC": per_period, "SpatialTaskState": per_period}
    for n in range(1, drives + 1):
        rates[f"DriveStatus{n}"] = per_period
        rates[f"DriveCommand{n}"] = per_period
        rates[f"ControllerState{n}"] = per_period
        rates[f"Heartbeat{n}"] = 1.0 / HEARTBEAT_PERIOD
    rates["CameraFrame"] = camera_rate
    for m in range(markers):
        rates[f"CameraMarker3D{m}"] = camera_rate
    return rates
