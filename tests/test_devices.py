"""Unit tests of the plant's device nodes (hil/devices.py), driven SYNC by SYNC without FMUs.

DriveNode is the drive firmware: latching by counter, stale/missed counting, the command timeout
at exactly `timeout_ticks`, the over-pressure guard (either side, release below 90 %, moves only
towards the sealing position), its EMCY and heartbeat frames and its status frame. CameraNode
is the camera: exposure, latency, the exposure offset it reports and the frame index. The camera
is checked against the controller's own idea of when frames are due (CameraTiming), so the two
sides of the bus cannot drift apart unnoticed.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from controllers.config import CameraTiming
from hil.devices import (
    EMERGENCY,
    FAULT_COMMAND_TIMEOUT,
    FAULT_OVER_PRESSURE,
    FAULT_REF_CLAMPED,
    HEARTBEAT,
    MEASUREMENT,
    STATUS,
    CameraNode,
    DriveNode,
    SyncContext,
)
from hil.vision import Camera, CameraEffects
from rigbus.protocol import (
    EMCY_COMMAND_TIMEOUT,
    EMCY_OVER_PRESSURE,
    NMT_OPERATIONAL,
    CameraMarker,
    DriveCommand,
    DriveStatus,
    Emcy,
    Heartbeat,
    Protocol,
    Sync,
)

NODE = 3
X_SEAL = 0.025  # [m]
LIMIT = 10e3  # [Pa] max_pressure
TIMEOUT = 3  # [ticks]
POSITION_RANGE = (0.0, 0.1)  # DriveStatus.piston_position in the DBC
PRESSURE_RANGE = (-101325.0, 300000.0)  # DriveStatus.p_a, p_b in the DBC


def drive(timeout_ticks: int = TIMEOUT) -> DriveNode:
    return DriveNode(
        NODE,
        x_start=X_SEAL,
        x_seal=X_SEAL,
        max_pressure=LIMIT,
        timeout_ticks=timeout_ticks,
        position_range=POSITION_RANGE,
        pressure_range=PRESSURE_RANGE,
    )


def sync(cycle: int, ticks_per_cycle: int = 1, heartbeat: bool = False) -> SyncContext:
    tick = cycle * ticks_per_cycle
    return SyncContext(cycle, tick, tick * 1e-3, heartbeat)


def inputs(
    x: float = X_SEAL, p_a: float = 0.0, p_b: float = 0.0, servo_fault: int = 0
) -> dict[str, float]:
    return {"x": x, "p_a": p_a, "p_b": p_b, "servo_fault": float(servo_fault)}


def of_type(sent, cls) -> list:
    return [frame for _, frame in sent if isinstance(frame, cls)]


def status_of(sent) -> DriveStatus:
    (status,) = of_type(sent, DriveStatus)
    return status


def command(setpoint: float, counter: int, enable: bool = True, node: int = NODE) -> DriveCommand:
    return DriveCommand(node, setpoint, enable, counter)


# ---------------------------------------------------------------------------- status frame


def test_status_echoes_the_sync_with_every_field_in_its_place() -> None:
    d = drive(timeout_ticks=1000)
    sent = d.act(sync(7), inputs(x=0.031, p_a=1234.0, p_b=-567.0, servo_fault=2))
    assert sent == [(STATUS, DriveStatus(NODE, 0.031, 1234.0, -567.0, 2, 7))]
    # and on the wire: p_a is the signal at bit 16, p_b the one at bit 32 (DBC), fault echoed
    message = Protocol().encode(sent[0][1])
    assert message.arbitration_id == 0x180 + NODE
    assert bytes(message.data[2:4]) == (123).to_bytes(2, "little", signed=True)
    assert bytes(message.data[4:6]) == (-57).to_bytes(2, "little", signed=True)


@pytest.mark.parametrize(
    ("given", "reported"),
    [
        (inputs(x=0.2), (0.1, 0.0, 0.0)),
        (inputs(x=-1e-3), (0.0, 0.0, 0.0)),
        (inputs(p_a=5e5, p_b=-2e5), (X_SEAL, 300000.0, -101325.0)),
        (inputs(p_a=-2e5, p_b=5e5), (X_SEAL, -101325.0, 300000.0)),
        (inputs(x=math.nan, p_b=math.nan), (0.0, 0.0, 0.0)),  # a NaN reads as 0
    ],
)
def test_status_is_saturated_to_the_dbc_range_as_an_adc_would(given, reported) -> None:
    status = status_of(drive().act(sync(1), given))
    assert (status.piston_position, status.p_a, status.p_b) == reported
    Protocol().encode(status)  # always encodable: a sensor reading never stops the plant


def test_servo_fault_bits_and_firmware_bits_combine() -> None:
    d = drive(timeout_ticks=1000)
    assert status_of(d.act(sync(1), inputs(servo_fault=1 | 4))).fault == 5
    status = status_of(d.act(sync(2), inputs(p_a=LIMIT + 1.0, servo_fault=2)))
    assert status.fault == 2 | FAULT_OVER_PRESSURE
    assert d.get_outputs()["fault"] == float(2 | FAULT_OVER_PRESSURE)


def test_syncs_after_a_period_with_the_setpoint_clamped_are_counted_with_the_first() -> None:
    """The servo's bit 2 at a SYNC says the last period's setpoint lay outside the stroke: the
    drive counts such SYNCs and keeps the first, with the setpoint it had given the servo."""
    d = drive(timeout_ticks=1000)
    d.receive(command(0.07, 0))
    d.act(sync(1), inputs())  # latched: the servo gets 0.07 from SYNC 1 on
    assert d.clamped == 0 and d.first_clamped is None
    d.act(sync(2), inputs(servo_fault=FAULT_REF_CLAMPED))
    d.act(sync(3), inputs(servo_fault=1))  # the end stop alone is not a clamped setpoint
    d.act(sync(4), inputs(servo_fault=FAULT_REF_CLAMPED | 4))
    d.act(sync(5), inputs(servo_fault=1 | 4))  # nor the stall
    assert d.clamped == 2 and d.first_clamped == (sync(2).time, 0.07)
    assert FAULT_REF_CLAMPED == 2


def test_the_plant_sums_clamped_syncs_over_its_drives_and_names_the_earliest() -> None:
    from types import SimpleNamespace

    from hil.plant import Plant, PlantStats

    drives = [DriveNode(n, X_SEAL, X_SEAL, LIMIT, 1000) for n in (1, 2, 3)]
    drives[0].clamped, drives[0].first_clamped = 3, (0.05, 0.07)
    drives[1].clamped, drives[1].first_clamped = 2, (0.03, -0.01)
    drives[2].clamped, drives[2].first_clamped = 1, (0.03, 0.09)  # at the same SYNC: drive 2
    plant = SimpleNamespace(stats=PlantStats(), nodes=[object(), *drives])
    Plant._count(plant)  # type: ignore[arg-type]
    assert plant.stats.setpoints_clamped == 6
    assert plant.stats.first_clamped == "drive2 at t = 0.030 s, setpoint -0.01 m"


def test_heartbeat_only_at_heartbeat_syncs_in_its_phase() -> None:
    d = drive(timeout_ticks=1000)
    assert of_type(d.act(sync(1), inputs()), Heartbeat) == []
    sent = d.act(sync(2, heartbeat=True), inputs())
    assert (HEARTBEAT, Heartbeat(NODE, NMT_OPERATIONAL)) in sent
    assert [phase for phase, _ in sent] == [HEARTBEAT, STATUS]


def test_send_phases_are_in_the_documented_order() -> None:
    # emergencies, heartbeats, measurements (camera), status: the plant sorts by these
    assert EMERGENCY < HEARTBEAT < MEASUREMENT < STATUS


# ---------------------------------------------------------------------------- latching


def test_command_of_the_previous_cycle_is_latched_at_sync_only() -> None:
    d = drive()
    assert d.get_outputs() == {"x_ref": X_SEAL, "enable": 1.0, "fault": 0.0}
    d.act(sync(0), inputs())
    assert d.accepts(command(0.030, 0))
    d.receive(command(0.030, 0, enable=False))
    # between SYNCs the outputs hold (synchronous RPDO)
    assert d.get_outputs()["x_ref"] == X_SEAL
    d.act(sync(1), inputs())
    assert d.get_outputs() == {"x_ref": 0.030, "enable": 0.0, "fault": 0.0}
    assert (d.stale, d.missed) == (0, 0)


def test_only_its_own_commands_are_accepted() -> None:
    d = drive()
    assert not d.accepts(command(0.03, 0, node=NODE + 1))
    assert not d.accepts(DriveStatus(NODE, 0.0, 0.0, 0.0, 0, 0))
    assert not d.accepts(Sync(0))


@pytest.mark.parametrize("counter", [5, 7, 8, 0])
def test_a_command_not_answering_the_previous_sync_is_stale(counter: int) -> None:
    d = drive(timeout_ticks=1000)
    d.receive(command(0.030, counter))
    d.act(sync(7), inputs())  # due: counter 6
    assert d.get_outputs()["x_ref"] == X_SEAL
    assert (d.stale, d.missed) == (1, 0)


def test_latching_follows_the_counter_across_its_wrap() -> None:
    d = drive(timeout_ticks=1000)
    d.receive(command(0.031, 255))
    d.act(sync(256), inputs())
    assert d.get_outputs()["x_ref"] == 0.031
    d.receive(command(0.032, 256 % 256))
    d.act(sync(257), inputs())
    assert d.get_outputs()["x_ref"] == 0.032
    d.receive(command(0.033, 257 % 256))  # answering SYNC 257, as decoded from the wire
    d.act(sync(258), inputs())
    assert d.get_outputs()["x_ref"] == 0.033
    assert (d.stale, d.missed) == (0, 0)


def test_the_last_command_of_a_period_wins() -> None:
    d = drive()
    d.receive(command(0.030, 0))
    d.receive(command(0.035, 0))
    d.act(sync(1), inputs())
    assert d.get_outputs()["x_ref"] == 0.035


def test_missing_commands_are_counted_except_before_the_first_sync() -> None:
    d = drive(timeout_ticks=1000)
    d.act(sync(0), inputs())
    assert d.missed == 0
    d.act(sync(1), inputs())
    d.act(sync(2), inputs())
    assert (d.missed, d.stale) == (2, 0)


# ---------------------------------------------------------------------------- command timeout


def test_timeout_trips_one_tick_after_timeout_ticks_not_at_it() -> None:
    d = drive(timeout_ticks=TIMEOUT)
    d.receive(command(0.040, 0))
    d.act(sync(1), inputs(x=0.026))  # latched at tick 1
    # SYNC at tick 1 + TIMEOUT: exactly timeout_ticks without a command is still fine
    sent = d.act(sync(1 + TIMEOUT), inputs(x=0.027))
    assert of_type(sent, Emcy) == [] and not d.timed_out
    assert d.get_outputs()["x_ref"] == 0.040
    # one tick later it holds the piston where it is, with one EMCY
    sent = d.act(sync(2 + TIMEOUT), inputs(x=0.028, p_a=2000.0, p_b=-1500.0))
    assert of_type(sent, Emcy) == [Emcy(NODE, EMCY_COMMAND_TIMEOUT, 1, 2000.0, 2 + TIMEOUT)]
    assert [phase for phase, _ in sent] == [EMERGENCY, STATUS]
    assert d.get_outputs()["x_ref"] == 0.028
    assert status_of(sent).fault == FAULT_COMMAND_TIMEOUT
    # it keeps holding the position of the SYNC at which it timed out, with no further EMCY
    sent = d.act(sync(3 + TIMEOUT), inputs(x=0.029))
    assert of_type(sent, Emcy) == [] and d.get_outputs()["x_ref"] == 0.028
    assert d.emcy_sent == 1
    # a fresh command ends the hold and clears the fault bit
    d.receive(command(0.035, 3 + TIMEOUT))
    sent = d.act(sync(4 + TIMEOUT), inputs(x=0.029))
    assert d.get_outputs()["x_ref"] == 0.035 and status_of(sent).fault == 0


def test_timeout_boundary_in_ticks_with_a_coarser_sync() -> None:
    # 10 ticks per SYNC, timeout 20 ticks: commanded at SYNC 1 (tick 10), silent after it;
    # SYNC 3 (tick 30, 20 ticks later) still acts, SYNC 4 (tick 40) times out
    d = drive(timeout_ticks=20)
    d.receive(command(0.030, 0))
    d.act(sync(1, 10), inputs())
    assert not of_type(d.act(sync(2, 10), inputs()), Emcy)
    assert not of_type(d.act(sync(3, 10), inputs()), Emcy)
    assert of_type(d.act(sync(4, 10), inputs()), Emcy)[0].error_code == EMCY_COMMAND_TIMEOUT


def test_a_drive_never_commanded_times_out_from_tick_zero() -> None:
    d = drive(timeout_ticks=TIMEOUT)
    for cycle in range(TIMEOUT + 1):
        assert not of_type(d.act(sync(cycle), inputs()), Emcy), cycle
    assert of_type(d.act(sync(TIMEOUT + 1), inputs()), Emcy)


def test_stale_commands_do_not_feed_the_watchdog() -> None:
    d = drive(timeout_ticks=TIMEOUT)
    d.receive(command(0.030, 0))
    d.act(sync(1), inputs())
    for cycle in range(2, 3 + TIMEOUT):
        d.receive(command(0.030, 200))  # never the due counter
        d.act(sync(cycle), inputs())
    assert d.timed_out and d.stale == TIMEOUT + 1


# ---------------------------------------------------------------------------- over-pressure


@pytest.mark.parametrize(
    ("p_a", "p_b"),
    [(LIMIT + 10.0, 0.0), (0.0, LIMIT + 10.0), (-(LIMIT + 10.0), 0.0), (0.0, -(LIMIT + 10.0))],
)
def test_over_pressure_on_either_side_holds_and_sends_one_emcy(p_a: float, p_b: float) -> None:
    d = drive(timeout_ticks=1000)
    d.receive(command(0.040, 0))
    sent = d.act(sync(1), inputs(x=0.030, p_a=p_a, p_b=p_b))
    (emcy,) = of_type(sent, Emcy)
    assert (emcy.node, emcy.error_code, emcy.error_register, emcy.counter) == (
        NODE,
        EMCY_OVER_PRESSURE,
        1,
        1,
    )
    assert emcy.pressure == max(p_a, p_b)  # the larger gauge pressure, as documented
    assert sent[0][0] == EMERGENCY
    assert status_of(sent).fault == FAULT_OVER_PRESSURE
    assert d.get_outputs()["x_ref"] == 0.030  # 40 mm is away from the seal: held
    # still above the limit at the next SYNC: no second EMCY
    assert not of_type(d.act(sync(2), inputs(x=0.030, p_a=p_a, p_b=p_b)), Emcy)
    assert d.emcy_sent == 1


def test_at_the_limit_is_not_over_it() -> None:
    d = drive(timeout_ticks=1000)
    assert not of_type(d.act(sync(1), inputs(p_a=LIMIT, p_b=-LIMIT)), Emcy)
    assert not d.over_pressure


def test_over_pressure_releases_only_when_both_sides_fall_below_90_percent() -> None:
    d = drive(timeout_ticks=1000)
    d.act(sync(1), inputs(p_a=LIMIT + 1.0))
    for cycle, (p_a, p_b) in enumerate(
        [(0.95 * LIMIT, 0.0), (0.89 * LIMIT, -0.95 * LIMIT), (0.5 * LIMIT, 0.91 * LIMIT)], start=2
    ):
        d.act(sync(cycle), inputs(p_a=p_a, p_b=p_b))
        assert d.over_pressure, (p_a, p_b)
    sent = d.act(sync(5), inputs(p_a=0.89 * LIMIT, p_b=-0.89 * LIMIT))
    assert not d.over_pressure and status_of(sent).fault == 0
    # and a new excursion trips it again with a new EMCY
    assert of_type(d.act(sync(6), inputs(p_b=LIMIT + 1.0)), Emcy)
    assert d.emcy_sent == 2


@pytest.mark.parametrize(
    ("x", "setpoint", "applied"),
    [
        (0.035, 0.040, 0.035),  # beyond the seal, further away: held
        (0.035, 0.030, 0.030),  # back towards the seal: allowed
        (0.035, 0.020, 0.020),  # towards and past the seal: allowed (it relieves first)
        (0.015, 0.010, 0.015),  # below the seal, further away: held
        (0.015, 0.020, 0.020),  # back towards the seal: allowed
        (0.015, 0.015, 0.015),  # standing still
    ],
)
def test_over_pressure_allows_only_moves_towards_the_seal(
    x: float, setpoint: float, applied: float
) -> None:
    d = drive(timeout_ticks=1000)
    d.receive(command(setpoint, 0))
    d.act(sync(1), inputs(x=x, p_a=LIMIT + 1.0, p_b=-(LIMIT + 1.0)))
    assert d.over_pressure
    assert d.get_outputs()["x_ref"] == applied


def test_without_over_pressure_the_command_moves_freely_away_from_the_seal() -> None:
    d = drive(timeout_ticks=1000)
    d.receive(command(0.045, 0))
    d.act(sync(1), inputs(x=0.035, p_a=0.9 * LIMIT))
    assert d.get_outputs()["x_ref"] == 0.045


def test_timeout_and_over_pressure_together_send_both_emcy_in_the_emergency_phase() -> None:
    d = drive(timeout_ticks=0)
    sent = d.act(sync(1), inputs(x=0.03, p_a=LIMIT + 1.0))
    assert [e.error_code for e in of_type(sent, Emcy)] == [
        EMCY_COMMAND_TIMEOUT,
        EMCY_OVER_PRESSURE,
    ]
    assert [phase for phase, _ in sent] == [EMERGENCY, EMERGENCY, STATUS]
    assert status_of(sent).fault == FAULT_COMMAND_TIMEOUT | FAULT_OVER_PRESSURE


# ---------------------------------------------------------------------------- camera


def marker_model(values) -> np.ndarray:
    """Two markers whose coordinates show the input at exposure (a tick count in metres/1000)."""
    k = values[0]
    return np.array([[k * 1e-3, -k * 1e-3], [0.1, k * 2e-3]])


def camera(
    period: int, latency: int, noise: float = 0.0, seed: int = 0, jitter: float = 0.0
) -> CameraNode:
    effects = CameraEffects(noise=noise, jitter=jitter)
    model = Camera(effects, np.random.default_rng(seed), period * 1e-3, 1e-3)
    return CameraNode(["kappa_1"], marker_model, latency, model)


def run_camera(
    node: CameraNode, ticks: int, ticks_per_sync: int
) -> list[tuple[int, list[CameraMarker]]]:
    """Expose at the camera's rate (input = the tick), SYNC every ticks_per_sync; what each SYNC
    delivers (as the master does: exposures step before the SYNC of the same tick acts)."""
    delivered = []
    for tick in range(ticks + 1):
        if tick % node.decimation == 0:
            node.set_inputs({"kappa_1": float(tick)})
            node.step(tick * 1e-3, node.decimation * 1e-3)
        if tick % ticks_per_sync == 0:
            sent = node.act(SyncContext(tick // ticks_per_sync, tick, tick * 1e-3), {})
            assert all(phase == MEASUREMENT for phase, _ in sent)
            # the markers of each picture (its CameraFrame header is tested with the controller)
            delivered.append((tick, [f for _, f in sent if isinstance(f, CameraMarker)]))
    return delivered


@pytest.mark.parametrize("latency", [0, 1, 3, 6, 10, 14])
def test_a_frame_arrives_exactly_latency_ticks_after_its_exposure(latency: int) -> None:
    delivered = run_camera(camera(period=5, latency=latency), ticks=60, ticks_per_sync=1)
    for tick, markers in delivered:
        exposed = tick - latency
        if exposed >= 0 and exposed % 5 == 0:
            index = exposed // 5
            assert [m.marker_id for m in markers] == [0, 1]
            assert {m.frame_index for m in markers} == {index}
            assert markers[0].x == pytest.approx(exposed * 1e-3)
            assert markers[1].y == pytest.approx(exposed * 2e-3)
            assert all(m.exposure_offset == pytest.approx(latency * 1e-3) for m in markers)
        else:
            assert markers == [], tick


def test_a_coarser_sync_delivers_every_frame_once_oldest_first_with_its_own_offset() -> None:
    # camera every 4 ticks, latency 6, SYNC every 10 ticks: frame j (exposed at 4 j) is at the
    # first SYNC at or after 4 j + 6, and reports SYNC tick - 4 j
    delivered = run_camera(camera(period=4, latency=6), ticks=100, ticks_per_sync=10)
    seen = []
    for tick, markers in delivered:
        indices = [m.frame_index for m in markers]
        assert indices == sorted(indices)
        for m in markers:
            exposed = 4 * m.frame_index
            assert exposed + 6 <= tick < exposed + 6 + 10
            assert m.exposure_offset == pytest.approx((tick - exposed) * 1e-3)
            assert m.x == pytest.approx(exposed * 1e-3) or m.marker_id == 1
        seen += sorted(set(indices))
    assert seen == list(range(len(seen))) and len(seen) == (100 - 6) // 4 + 1


@pytest.mark.parametrize(
    ("period", "latency", "control"),
    [(10, 6, 10), (10, 10, 10), (10, 0, 10), (5, 6, 10), (20, 6, 10), (10, 16, 10), (4, 7, 6)],
)
def test_the_camera_delivers_what_the_controller_expects(
    period: int, latency: int, control: int
) -> None:
    """CameraTiming.frames_due (controller) and CameraNode (plant) agree at every SYNC."""
    timing = CameraTiming(period, latency, control, markers=2)
    delivered = run_camera(camera(period, latency), ticks=30 * control, ticks_per_sync=control)
    count = 0
    for cycle, (_, markers) in enumerate(delivered):
        count += len({m.frame_index for m in markers})
        assert count == timing.frames_due(cycle), cycle


@pytest.mark.parametrize(
    ("period", "latency", "control", "jitter", "bound"),
    [
        (10, 6, 10, 5e-3, 9),
        (10, 6, 10, 9e-3, 9),
        (5, 3, 10, 4e-3, 4),
        (4, 7, 6, 3e-3, 3),
        (10, 8, 10, 0.5e-3, 3),
    ],
)
def test_a_jittered_camera_delivers_every_frame_the_controller_waits_for(
    period: int, latency: int, control: int, jitter: float, bound: int
) -> None:
    """With exposure jitter a picture comes up to `bound` ticks late (6 sigma, below the
    period): the controller, told the bound (delay_ticks), waits for no frame before the plant
    can have sent it (it waited for frames the camera had not taken yet, and a strict run
    failed after its timeout), and for every frame by the SYNC its latest exposure allows."""
    node = camera(period, latency, jitter=jitter, seed=7)
    assert node.camera.max_delay_ticks == bound
    timing = CameraTiming(period, latency, control, markers=2, delay_ticks=bound)
    delivered = run_camera(node, ticks=60 * control, ticks_per_sync=control)
    count = 0
    late = 0
    for cycle, (_, markers) in enumerate(delivered):
        count += len({m.frame_index for m in markers})
        assert count >= timing.frames_due(cycle), cycle
        late += count < CameraTiming(period, latency, control, markers=2).frames_due(cycle)
    if bound == period - 1:  # jitter of the order of the period: frames come a SYNC late
        assert late > 0  # the jitter-free count would have waited on frames not yet sent


def test_frame_indices_count_on_past_255_and_wrap_on_the_wire() -> None:
    node = camera(period=1, latency=0)
    delivered = run_camera(node, ticks=300, ticks_per_sync=1)
    indices = [markers[0].frame_index for _, markers in delivered]
    assert indices == list(range(301))
    protocol = Protocol()
    wire = protocol.decode(protocol.encode(delivered[257][1][0]))
    assert wire.frame_index == 1


def test_camera_noise_is_seeded_and_zero_noise_is_exact() -> None:
    def points(noise: float, seed: int) -> list[float]:
        delivered = run_camera(camera(10, 0, noise, seed), ticks=50, ticks_per_sync=10)
        return [m.x for _, markers in delivered for m in markers]

    exact = points(0.0, 1)
    assert exact == pytest.approx([0.0, 0.1, 0.01, 0.1, 0.02, 0.1, 0.03, 0.1, 0.04, 0.1, 0.05, 0.1])
    assert points(1e-3, 1) == points(1e-3, 1)
    assert points(1e-3, 1) != points(1e-3, 2)
    assert 0 < np.max(np.abs(np.subtract(points(1e-3, 1), exact))) < 5e-3


def test_a_marker_outside_the_field_of_view_is_not_seen() -> None:
    # marker 0 walks out along x (k mm at tick k), marker 1 stays at x = 0.1 m
    model = Camera(CameraEffects(), np.random.default_rng(0), 5e-3, 1e-3)
    node = CameraNode(["kappa_1"], marker_model, 0, model, field=((-0.02, 0.02), (-1.0, 1.0)))
    delivered = run_camera(node, ticks=40, ticks_per_sync=5)
    seen = {tick: [m.marker_id for m in markers] for tick, markers in delivered if markers}
    assert seen[20] == [0]
    assert all(ids == [0] for tick, ids in seen.items() if tick <= 20)  # 0.1 m is out: never 1
    assert all(0 not in ids for tick, ids in seen.items() if tick > 20)  # x > 0.02 m: 0 is gone


@pytest.mark.parametrize("dims", [2, 3])
def test_the_field_of_view_bounds_every_axis_on_both_sides_edges_included(dims: int) -> None:
    """A marker is seen inside the field, on its edges too; beyond any bound of any axis, or
    with a NaN coordinate, it is not."""
    model = Camera(CameraEffects(), np.random.default_rng(0), 5e-3, 1e-3)
    field = ((-0.1, 0.2), (-0.3, 0.4), (-0.5, 0.6))[:dims]
    node = CameraNode(["kappa_1"], marker_model, 0, model, field=field, dims=dims)
    inside = [0.0] * dims
    points = [inside, [lo for lo, _ in field], [hi for _, hi in field]]  # seen: 0, 1, 2
    for axis, (lo, hi) in enumerate(field):
        for value in (lo - 1e-9, hi + 1e-9, math.nan):
            point = list(inside)
            point[axis] = value
            points.append(point)
    assert node._in_view(points) == [0, 1, 2]
