"""Unit tests of the controller side without a plant: camera timing and frame assembly, the
newest-frame estimator, the curvature PI, bus specs, the real-time clock (with a fake clock, no
waiting), and the controller node's frame handling on a scripted bus (status counters, camera
frames arriving in any order).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import replace

import can
import numpy as np
import pytest

from controllers import kinematics
from controllers.config import CameraTiming
from controllers.curvature import CurvaturePI, PiGains
from controllers.estimation import BendModel, Estimate, MarkerFrame
from controllers.estimators import RawEstimator
from controllers.node import CameraAssembler, ControllerError, ControllerNode, RealtimeClock
from rigbus.canbus import DEFAULT_CHANNEL, DEFAULT_LOOPBACK_PORT, BusSpec
from rigbus.protocol import (
    CameraFrame,
    CameraMarker,
    DriveCommand,
    DriveStatus,
    Emcy,
    Frame,
    Heartbeat,
    Protocol,
    Sync,
)
from robots.planar_arm.controller.config import ControllerConfig

# ---------------------------------------------------------------------------- CameraTiming


def brute_force_due(timing: CameraTiming, cycle: int) -> int:
    """Frames j whose latest exposure j * period + delay, plus the latency, is at or before SYNC
    cycle's tick."""
    sync_tick = cycle * timing.control_ticks
    return sum(
        1
        for j in range(10_000)
        if j * timing.period_ticks + timing.delay_ticks + timing.latency_ticks <= sync_tick
    )


@pytest.mark.parametrize(
    ("period", "latency", "control", "delay"),
    [
        (10, 6, 10, 0),
        (10, 10, 10, 0),
        (10, 0, 10, 0),
        (5, 6, 10, 0),
        (20, 6, 10, 0),
        (10, 16, 10, 0),
        (3, 7, 4, 0),
        (10, 6, 10, 9),
        (10, 6, 10, 4),
        (5, 6, 10, 4),
        (3, 7, 4, 2),
    ],
)
def test_frames_due_counts_every_frame_available_by_the_sync(
    period: int, latency: int, control: int, delay: int
) -> None:
    timing = CameraTiming(period, latency, control, markers=2, delay_ticks=delay)
    for cycle in range(60):
        assert timing.frames_due(cycle) == brute_force_due(timing, cycle), cycle


def test_frames_due_at_the_boundary() -> None:
    timing = CameraTiming(period_ticks=10, latency_ticks=10, control_ticks=10, markers=2)
    # frame 0 is available at tick 10, exactly SYNC 1: due then, not one cycle later
    assert [timing.frames_due(c) for c in range(4)] == [0, 1, 2, 3]
    default = CameraTiming(period_ticks=10, latency_ticks=6, control_ticks=10, markers=2)
    assert [default.frames_due(c) for c in range(4)] == [0, 1, 2, 3]
    fast = CameraTiming(period_ticks=5, latency_ticks=6, control_ticks=10, markers=2)
    assert [fast.frames_due(c) for c in range(4)] == [0, 1, 3, 5]


# ---------------------------------------------------------------------------- CameraAssembler


def marker(m: int, frame: int, offset: float = 0.006) -> CameraMarker:
    return CameraMarker(m, 0.1 * m + 1e-3 * frame, -0.1 * m, frame % 256, offset)


def header(frame: int, markers: int, offset: float = 0.006) -> CameraFrame:
    """The picture's CameraFrame: it holds markers 0 .. markers - 1."""
    return CameraFrame(frame % 256, offset, (1 << markers) - 1, markers)


def test_a_frame_is_complete_only_with_every_marker_of_its_own_index() -> None:
    assembler = CameraAssembler(markers=3)
    assembler.add(header(5, 3))
    assembler.add(header(6, 3))
    assembler.add(marker(0, 5))
    assembler.add(marker(1, 5))
    assembler.add(marker(2, 6))  # the next frame's marker does not complete frame 5
    assert not assembler.complete(5) and not assembler.complete(6)
    assembler.add(marker(2, 4))  # nor does an older frame's
    assert not assembler.complete(5)
    assembler.add(marker(2, 5, offset=0.008))
    assert assembler.complete(5) and not assembler.complete(6)


def test_take_gives_the_frame_asked_for_with_its_exposure_time() -> None:
    assembler = CameraAssembler(markers=2)
    for frame in (7, 8):
        for m in (1, 0):  # any arrival order
            assembler.add(marker(m, frame, offset=0.001 * frame))
        assembler.add(header(frame, 2, offset=0.001 * frame))
    taken = assembler.take(7, sync_time=0.5)
    assert taken.exposure_time == pytest.approx(0.5 - 0.007)
    np.testing.assert_allclose(taken.points, [[0.007, 0.0], [0.107, -0.1]], atol=1e-15)
    assert not assembler.complete(7)  # taken
    assert assembler.complete(8)
    np.testing.assert_allclose(
        assembler.take(8, 0.5).points, [[0.008, 0.0], [0.108, -0.1]], atol=1e-15
    )


def test_frame_indices_wrap_modulo_256() -> None:
    assembler = CameraAssembler(markers=2)
    assembler.add(header(256 + 3, 2))
    for m in range(2):
        assembler.add(marker(m, 256 + 3))  # on the wire: frame_index 3
    assert assembler.complete(259)
    assert assembler.take(259, 1.0).points[0, 0] == pytest.approx(0.259)
    assembler.add(marker(0, 255))
    assert assembler.drop(255) and not assembler.drop(255)
    assert not assembler.drop(300)


def test_markers_beyond_the_robots_are_ignored() -> None:
    assembler = CameraAssembler(markers=2)
    assembler.add(header(1, 2))
    assembler.add(marker(0, 1))
    assembler.add(marker(5, 1))
    assert not assembler.complete(1)


def test_a_picture_is_complete_with_the_markers_its_mask_names() -> None:
    """Only the markers its header's mask names (and the robot has) complete a picture: a
    marker it does not name counts for nothing, a mask bit beyond the robot's markers is no
    marker to wait for."""
    assembler = CameraAssembler(markers=3)
    assembler.add(CameraFrame(4, 0.006, 0b101, 2))  # markers 0 and 2 seen
    assembler.add(marker(0, 4))
    assembler.add(marker(1, 4))  # as many markers in as the mask names, but not the right ones
    assert not assembler.complete(4)
    assembler.add(marker(2, 4))
    assert assembler.complete(4)
    points = assembler.take(4, 1.0).points
    assert np.isnan(points[1]).all() and not np.isnan(points[[0, 2]]).any()
    assembler.add(CameraFrame(5, 0.006, 0b11011, 4))  # bits 3 and 4: no such markers
    assembler.add(marker(0, 5))
    assert not assembler.complete(5)
    assembler.add(marker(1, 5))
    assert assembler.complete(5)


# ---------------------------------------------------------------------------- raw estimator

LENGTHS = (0.06, 0.05)
BASE = (0.0, 0.0, np.pi / 2)


def frame_of(kappas, time: float) -> MarkerFrame:
    return MarkerFrame(time, kinematics.markers(kappas, LENGTHS, BASE))


def test_the_raw_estimator_uses_the_newest_complete_frame() -> None:
    bends = [BendModel(L, 1e-6, 0.025, 6e-3, 7.7e-7) for L in LENGTHS]
    estimator = RawEstimator(bends, BASE)
    older, newer = frame_of([5.0, -3.0], 0.001), frame_of([8.0, 2.0], 0.006)
    estimate = estimator.update(0.01, {}, [older, newer])
    np.testing.assert_allclose(estimate.kappa, [8.0, 2.0], atol=1e-9)
    assert estimate.measured == 4  # segments inverted: two per complete frame
    # an incomplete newest frame does not count; the newest complete one does
    partial = MarkerFrame(0.016, newer.points.copy())
    partial.points[2] = np.nan
    estimate = estimator.update(0.02, {}, [frame_of([1.0, 1.0], 0.011), partial])
    np.testing.assert_allclose(estimate.kappa, [1.0, 1.0], atol=1e-9)
    # no frame: the last value holds
    np.testing.assert_allclose(estimator.update(0.03, {}, []).kappa, [1.0, 1.0], atol=1e-9)


# ---------------------------------------------------------------------------- CurvaturePI

GAINS = PiGains(Kp=2e-3, Ki=1e-2)
T = 0.01


def pi(**changes) -> CurvaturePI:
    values = dict(gains=GAINS, period=T, x_mid=0.025, x_min=0.0, x_max=0.05, feedforward=1e-3)
    values.update(changes)
    return CurvaturePI(**values)  # type: ignore[arg-type]


def test_pi_law_with_feedforward() -> None:
    c = pi()
    # e = 2: x_mid + ff ref + Kp e + Ki e T
    assert c.update(3.0, 1.0) == pytest.approx(0.025 + 3e-3 + 4e-3 + 2e-4)
    assert c.integral == pytest.approx(2e-4)
    assert c.update(3.0, 1.0) == pytest.approx(0.025 + 3e-3 + 4e-3 + 4e-4)
    assert pi(feedforward=0.0).update(3.0, 3.0) == pytest.approx(0.025)


def test_pi_integrates_constant_error_linearly() -> None:
    c = pi()
    for _ in range(50):
        c.update(0.5, 0.0)
    assert c.integral == pytest.approx(50 * GAINS.Ki * 0.5 * T)


@pytest.mark.parametrize(("ref", "bound"), [(30.0, 0.05), (-30.0, 0.0)])
def test_pi_clamps_to_the_stroke_and_stops_integrating_against_the_clamp(
    ref: float, bound: float
) -> None:
    c = pi()
    for _ in range(20):
        assert c.update(ref, 0.0) == bound
    assert c.integral == 0.0  # no wind-up while pushing into the clamp


def test_pi_integrates_out_of_a_clamp() -> None:
    c = pi(x_mid=0.049, feedforward=0.0, gains=PiGains(Kp=1e-3, Ki=1e-2))
    c.integral = 5e-3  # wound up towards x_max
    # clamped at x_max while the error is negative: integrating unwinds, so it must go on
    assert c.update(0.0, 1.0) == 0.05
    assert c.integral == pytest.approx(5e-3 - 1e-2 * 1.0 * T)
    c = pi(x_mid=0.001, feedforward=0.0, gains=PiGains(Kp=1e-3, Ki=1e-2))
    c.integral = -5e-3
    assert c.update(1.0, 0.0) == 0.0
    assert c.integral == pytest.approx(-5e-3 + 1e-2 * T)


def test_pi_does_not_integrate_while_the_drive_is_slewing() -> None:
    c = pi()
    first = c.update(1.0, 0.0)
    integral = c.integral
    # the piston is 2 mm behind the previous setpoint (tolerance 1 mm): hold the integral
    c.update(1.0, 0.0, piston=first - 2e-3)
    assert c.integral == integral
    # within the tolerance: integrate
    c.update(1.0, 0.0, piston=c.previous - 0.5e-3)
    assert c.integral == pytest.approx(integral + GAINS.Ki * T)
    # no reading: integrate
    c.update(1.0, 0.0, piston=None)
    assert c.integral == pytest.approx(integral + 2 * GAINS.Ki * T)


# ---------------------------------------------------------------------------- BusSpec


@pytest.mark.parametrize(
    ("text", "spec"),
    [
        ("virtual", BusSpec("virtual", DEFAULT_CHANNEL)),
        ("virtual:rig7", BusSpec("virtual", "rig7")),
        ("loopback", BusSpec("loopback", DEFAULT_CHANNEL, "127.0.0.1", DEFAULT_LOOPBACK_PORT)),
        ("loopback:4000", BusSpec("loopback", DEFAULT_CHANNEL, "127.0.0.1", 4000)),
        ("loopback:10.0.0.2:4001", BusSpec("loopback", DEFAULT_CHANNEL, "10.0.0.2", 4001)),
        ("socketcan:vcan0", BusSpec("socketcan", "vcan0")),
    ],
)
def test_bus_spec_parse(text: str, spec: BusSpec) -> None:
    assert BusSpec.parse(text) == spec
    assert BusSpec.parse(str(spec)) == spec


def test_bus_spec_text_form() -> None:
    assert str(BusSpec.parse("loopback:4000")) == "loopback:127.0.0.1:4000"
    assert str(BusSpec.parse("virtual")) == f"virtual:{DEFAULT_CHANNEL}"
    assert str(BusSpec.parse("socketcan:can1")) == "socketcan:can1"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("loopback:port", "port must be an integer"),
        ("loopback:host:x1", "port must be an integer"),
        ("sockcan:vcan0", "neither loopback, virtual, config nor a python-can interface"),
        ("socketcan:vcan0,bitrate", "options are key=value"),
    ],
)
def test_bus_spec_errors_name_the_spec(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message) as info:
        BusSpec.parse(text)
    assert repr(text) in str(info.value)


# ---------------------------------------------------------------------------- RealtimeClock


class FakeTime:
    """A monotonic clock that only moves when slept on or told to (`work`)."""

    def __init__(self, start: float = 1000.0, oversleep: float = 0.0) -> None:
        self.now = start
        self.oversleep = oversleep
        self.sleeps: list[float] = []

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        assert seconds > 0.0
        self.sleeps.append(seconds)
        self.now += seconds + self.oversleep

    def work(self, seconds: float) -> None:
        self.now += seconds


def test_realtime_clock_sleeps_until_each_sync_is_due() -> None:
    fake = FakeTime()
    clock = RealtimeClock(0.01, sleep=fake.sleep, monotonic=fake.monotonic)
    assert clock.wait_for(0) == 0.0 and fake.sleeps == []  # SYNC 0 starts the clock
    fake.work(0.003)
    assert clock.wait_for(1) == 0.0
    assert fake.sleeps == pytest.approx([0.007])
    assert fake.now == pytest.approx(1000.01)
    fake.work(0.001)
    assert clock.wait_for(2) == 0.0
    assert fake.sleeps == pytest.approx([0.007, 0.009])
    assert fake.now == pytest.approx(1000.02)


def test_realtime_clock_reports_lateness_and_does_not_sleep_when_late() -> None:
    fake = FakeTime()
    clock = RealtimeClock(0.01, sleep=fake.sleep, monotonic=fake.monotonic)
    clock.wait_for(0)
    fake.work(0.025)  # an overrun: SYNC 1 and 2 are both past
    assert clock.wait_for(1) == pytest.approx(0.015)
    assert clock.wait_for(2) == pytest.approx(0.005)
    assert fake.sleeps == []
    # the schedule does not slip: SYNC 3 is still due at start + 3 T
    assert clock.wait_for(3) == 0.0
    assert fake.sleeps == pytest.approx([0.005])
    assert fake.now == pytest.approx(1000.03)


def test_realtime_clock_lateness_of_a_sleep_that_overshoots() -> None:
    fake = FakeTime(oversleep=0.0004)
    clock = RealtimeClock(0.01, sleep=fake.sleep, monotonic=fake.monotonic)
    clock.wait_for(0)
    assert clock.wait_for(1) == pytest.approx(0.0004)
    assert fake.sleeps == pytest.approx([0.01])


# ---------------------------------------------------------------------------- ControllerNode


class ScriptedBus:
    """A bus without a transport: every frame the node sends is answered at once by `answer`,
    whose frames queue up for the node's receive, in the order given."""

    def __init__(self, answer: Callable[[Frame], list[Frame]]) -> None:
        self.protocol = Protocol()
        self.answer = answer
        self.inbox: deque = deque()
        self.sent: list[Frame] = []

    def send(self, message, timeout=None) -> None:
        frame = self.protocol.decode(message)
        self.sent.append(frame)
        for reply in self.answer(frame):
            self.inbox.append(self.protocol.encode(reply))

    def recv(self, timeout=None):
        return self.inbox.popleft() if self.inbox else None


class RecordingEstimator:
    name = "recording"

    def __init__(self) -> None:
        self.calls: list[tuple[float, dict, list[MarkerFrame]]] = []

    def update(self, t, drives, frames) -> Estimate:
        self.calls.append((t, dict(drives), list(frames)))
        zero = np.zeros(1)
        return Estimate(zero, zero, zero)


class SilentController:
    def compute(self, cycle, t, estimate, drives) -> list:
        return []


def piston_at(cycle: int) -> float:
    return 0.02 + 1e-4 * cycle


def camera_point(frame: int, m: int) -> tuple[float, float]:
    return 0.01 * m + 1e-4 * frame, -0.02 * m


def config(policy: str, cycles: int, timing: CameraTiming) -> ControllerConfig:
    from hil.run import controller_config
    from hil.scenario import load_scenario

    return replace(
        controller_config(load_scenario()),
        policy=policy,
        cycles=cycles,
        camera_timing=timing,
        timeout=5.0,
    )


def rig_answer(timing: CameraTiming, stale_status: bool) -> Callable[[Frame], list[Frame]]:
    """The rig as the bus shows it, in an adversarial order: new camera frames newest first
    and their markers in reverse, then (optionally) a status echoing the previous SYNC, then
    the status of this SYNC."""

    def answer(frame: Frame) -> list[Frame]:
        if not isinstance(frame, Sync):
            return []
        c = frame.counter  # cycles stay below 256 here
        replies: list[Frame] = []
        new = range(timing.frames_due(c - 1) if c else 0, timing.frames_due(c))
        for j in reversed(new):
            offset = (c * timing.control_ticks - j * timing.period_ticks) * 1e-3
            for m in reversed(range(timing.markers)):
                replies.append(CameraMarker(m, *camera_point(j, m), j, offset))
            replies.append(CameraFrame(j, offset, (1 << timing.markers) - 1, timing.markers))
        if stale_status and c > 0:
            replies.append(DriveStatus(1, piston_at(c - 1), 0.0, 0.0, 0, c - 1))
        replies.append(DriveStatus(1, piston_at(c), 100.0 * c, -100.0 * c, 0, c))
        return replies

    return answer


FAST_CAMERA = CameraTiming(period_ticks=5, latency_ticks=6, control_ticks=10, markers=2)


def test_controller_hands_the_estimator_every_due_frame_oldest_first() -> None:
    estimator = RecordingEstimator()
    bus = ScriptedBus(rig_answer(FAST_CAMERA, stale_status=False))
    node = ControllerNode(
        config("strict", 12, FAST_CAMERA), bus, estimator=estimator, controller=SilentController()
    )
    report = node.run()
    # the last SYNC collects its frames too (nothing acts on them)
    assert report.camera_frames == FAST_CAMERA.frames_due(12)
    assert len(estimator.calls) == 12
    taken = 0
    for cycle, (t, drives, frames) in enumerate(estimator.calls):
        assert t == pytest.approx(cycle * 0.01)
        assert drives[1].piston_position == pytest.approx(piston_at(cycle), abs=1e-6)
        due = FAST_CAMERA.frames_due(cycle)
        assert len(frames) == due - taken, cycle
        for j, f in zip(range(taken, due), frames, strict=True):
            assert f.exposure_time == pytest.approx(j * 5e-3)  # exposure at tick 5 j
            np.testing.assert_allclose(f.points, [camera_point(j, 0), camera_point(j, 1)])
        taken = due


def test_strict_controller_stops_at_a_status_of_the_wrong_cycle() -> None:
    bus = ScriptedBus(rig_answer(FAST_CAMERA, stale_status=True))
    node = ControllerNode(
        config("strict", 5, FAST_CAMERA),
        bus,
        estimator=RecordingEstimator(),
        controller=SilentController(),
    )
    with pytest.raises(ControllerError, match=r"stale DriveStatus1 \(counter 0\) .* SYNC 1 "):
        node.run()


def test_lenient_controller_skips_stale_status_and_uses_the_one_of_its_cycle() -> None:
    estimator = RecordingEstimator()
    bus = ScriptedBus(rig_answer(FAST_CAMERA, stale_status=True))
    node = ControllerNode(
        config("hold", 8, FAST_CAMERA), bus, estimator=estimator, controller=SilentController()
    )
    report = node.run()
    assert report.stale_frames == 8 and report.status_missed == 0
    for cycle, (_, drives, _) in enumerate(estimator.calls):
        assert drives[1].piston_position == pytest.approx(piston_at(cycle), abs=1e-6)
        assert drives[1].p_a == pytest.approx(100.0 * cycle)
        assert drives[1].p_b == pytest.approx(-100.0 * cycle)
    assert [f.counter for f in bus.sent if isinstance(f, Sync)] == list(range(9))


GARBLED = can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False)  # 1 byte short


class InterferedBus(ScriptedBus):
    """The scripted rig, and before its replies to each SYNC the frames of `others` (other
    nodes, or a garbled frame), in that order."""

    def __init__(self, answer: Callable[[Frame], list[Frame]], others: list) -> None:
        super().__init__(answer)
        self.others = others
        self.delivered = 0  # messages handed to the node

    def recv(self, timeout=None):
        message = super().recv(timeout)
        self.delivered += message is not None
        return message

    def send(self, message, timeout=None) -> None:
        super().send(message, timeout)
        if isinstance(self.sent[-1], Sync):
            replies = [self.inbox.pop() for _ in range(len(self.inbox))][::-1]
            for other in self.others:
                self.inbox.append(
                    other if isinstance(other, can.Message) else self.protocol.encode(other)
                )
            self.inbox.extend(replies)


def test_a_garbled_frame_stops_the_strict_controller_naming_the_sync() -> None:
    bus = InterferedBus(rig_answer(FAST_CAMERA, stale_status=False), [GARBLED])
    node = ControllerNode(
        config("strict", 3, FAST_CAMERA),
        bus,
        estimator=RecordingEstimator(),
        controller=SilentController(),
    )
    with pytest.raises(ControllerError, match=r"^at SYNC 0: DriveStatus1 \(0x181\): 1 data bytes"):
        node.run()


def test_under_hold_frames_the_controller_cannot_use_are_counted_not_fatal() -> None:
    """A garbled frame and an unexpected one count as unknown, an EMCY is recorded with its
    cycle, a heartbeat is let pass, and a DriveCommand (only this controller sends it) or a
    second status of the cycle is an intrusion; the cycle's own status is still used."""
    others = [
        GARBLED,
        Emcy(1, 0x5000, 1, 0.0, 0),
        Heartbeat(1, 5),
        DriveCommand(1, 0.03, True, 0),
        CameraMarker(7, 0.0, 0.0, 0, 0.0),  # beyond the markers: ignored by the assembler
    ]
    estimator = RecordingEstimator()
    bus = InterferedBus(rig_answer(FAST_CAMERA, stale_status=False), others)
    node = ControllerNode(
        config("hold", 4, FAST_CAMERA), bus, estimator=estimator, controller=SilentController()
    )
    report = node.run()
    assert report.unknown_frames == 5  # one garbled frame per SYNC 0..4
    assert [e["cycle"] for e in report.emcy] == [0, 1, 2, 3, 4]
    assert report.emcy[0]["error_code"] == 0x5000
    assert report.intrusions == 5 and report.first_intrusion.startswith("DriveCommand 0x201")
    assert report.stale_frames == 0 and report.status_missed == 0
    assert report.frames_received == bus.delivered
    for cycle, (_, drives, _) in enumerate(estimator.calls):
        assert drives[1].piston_position == pytest.approx(piston_at(cycle), abs=1e-6)


def test_a_second_status_of_the_cycle_is_an_intrusion_and_strict_stops() -> None:
    """Another node sending DriveStatus1 too: its copy arrives while the cycle still waits for
    its camera frames (each SYNC waits for one here)."""
    timing = replace(FAST_CAMERA, latency_ticks=0)

    def twice(frame: Frame) -> list[Frame]:
        replies = rig_answer(timing, stale_status=False)(frame)
        status = [r for r in replies if isinstance(r, DriveStatus)]
        return status + status + [r for r in replies if not isinstance(r, DriveStatus)]

    node = ControllerNode(
        config("hold", 2, timing),
        ScriptedBus(twice),
        estimator=RecordingEstimator(),
        controller=SilentController(),
    )
    report = node.run()
    assert report.intrusions == 3 and report.stale_frames == 0
    assert report.first_intrusion == (
        "a second DriveStatus1 for SYNC 0: another node sends in the drive's name"
    )
    strict = ControllerNode(
        config("strict", 2, timing),
        ScriptedBus(twice),
        estimator=RecordingEstimator(),
        controller=SilentController(),
    )
    with pytest.raises(ControllerError, match=r"^intrusion on the bus: a second DriveStatus1 "):
        strict.run()


def test_under_hold_every_status_a_cycle_misses_is_counted() -> None:
    """The fish's cycle needs three status frames (both valves', the canister's); a rig that
    answers none leaves each cycle's wait to run out (a hundredth of a second here): three
    misses per SYNC, 0 to 2."""
    from hil.run import controller_config
    from hil.scenario import load_scenario, resolve_scenario

    fish = replace(
        controller_config(load_scenario(resolve_scenario("fish-escape"))),
        policy="hold",
        cycles=2,
        timeout=0.01,
        camera_timing=CameraTiming(
            period_ticks=5, latency_ticks=10**6, control_ticks=10, markers=3
        ),
    )
    estimator = RecordingEstimator()
    node = ControllerNode(
        fish, ScriptedBus(lambda frame: []), estimator=estimator, controller=SilentController()
    )
    report = node.run()
    assert report.status_missed == 9 and report.frames_received == 0
    assert [dict(drives) for _, drives, _ in estimator.calls] == [{}, {}]
