"""Whole-arm planning in confined spaces (robots/planar_arm/controller/confined.py: the channel
and the pipe sections; confined_planner.py: the planner): the channel's signed clearance
against closed forms, the sampled backbone against the kinematics, the four pipe sections planned
to their goals without penetration (at the waypoints and along the curvature moves between them),
monotonic advance, trust region, determinism, and the failures that must be reports, not
exceptions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controllers import kinematics
from robots.planar_arm.controller.confined import (
    KAPPA_LIMIT,
    MAX_VERTICES,
    MAX_WALLS,
    PIPES,
    WIDTH,
    Channel,
)
from robots.planar_arm.controller.confined_planner import (
    Plan,
    _target,
    plan_penetration,
    plan_whole_arm,
    sample_backbone,
)
from robots.planar_arm.controller.tasks import CurvatureMove

MARGIN = 2e-3  # [m] the planner's default margin beyond width / 2
STEP = 2.0  # [1/m] the planner's default trust region
LOWER = np.full(6, -KAPPA_LIMIT)
UPPER = np.full(6, KAPPA_LIMIT)
SAMPLES = 8


def corridor(half: float = 0.02, length: float = 1.0) -> Channel:
    """Two parallel walls y = +-half from x = 0 to `length`."""
    return Channel(
        (((0.0, half), (length, half)), ((0.0, -half), (length, -half))),
        ((0.0, 0.0), (length, 0.0)),
    )


def plan_pipe(name: str, **options: float) -> Plan:
    section = PIPES[name]
    return plan_whole_arm(
        section.start,
        section.goal,
        section.lengths,
        section.base,
        LOWER,
        UPPER,
        section.channel,
        **options,
    )


@pytest.fixture(scope="module")
def plans() -> dict[str, Plan]:
    return {name: plan_pipe(name) for name in PIPES}


# ---------------------------------------------------------------------- the channel


def test_clearance_of_a_straight_wall_is_the_distance_signed_by_the_side() -> None:
    channel = corridor(half=0.02)
    y = np.tile(np.linspace(-0.05, 0.05, 21), 3)
    x = np.repeat([0.03, 0.5, 0.98], 21)  # near both ends of the walls and between
    points = np.stack((x, y), axis=1)
    clearance, gradient = channel.clearance_and_gradient(points)
    # inside: the distance to the nearer wall; beyond a wall: minus the distance to it
    np.testing.assert_allclose(clearance, 0.02 - np.abs(y), atol=1e-15)
    # the gradient points away from the nearer wall inside, towards it outside: -sign(y) e_y
    nonzero = np.abs(y) > 1e-12
    np.testing.assert_allclose(gradient[nonzero, 1], -np.sign(y[nonzero]), atol=1e-12)
    np.testing.assert_allclose(gradient[:, 0], 0.0, atol=1e-12)


def test_clearance_at_a_corner_is_the_distance_to_the_vertex_or_the_edges() -> None:
    # an L-shaped corridor: the inner wall turns down at the origin (a reflex corner of the
    # allowed region), the outer wall runs around at distance 1
    channel = Channel(
        (((-1.0, 0.0), (0.0, 0.0), (0.0, -1.0)), ((-1.0, 1.0), (1.0, 1.0), (1.0, -1.0))),
        ((-1.0, 0.5), (0.5, 0.5), (0.5, -1.0)),
    )
    points = np.array([[0.1, 0.1], [0.3, 0.2], [-0.1, -0.1], [-0.3, -0.05], [0.5, 0.8]])
    clearance, gradient = channel.clearance_and_gradient(points)
    expected = [
        math.hypot(0.1, 0.1),  # nearest the corner vertex
        math.hypot(0.3, 0.2),
        -0.1,  # in the solid quadrant, 0.1 from both inner edges
        -0.05,  # nearest the horizontal inner edge
        0.2,  # nearest the outer wall's top
    ]
    np.testing.assert_allclose(clearance, expected, atol=1e-15)
    np.testing.assert_allclose(gradient[0], [math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(gradient[3], [0.0, 1.0], atol=1e-12)  # back up, out of the wall
    np.testing.assert_allclose(gradient[4], [0.0, -1.0], atol=1e-12)


def test_clearance_gradient_is_the_derivative() -> None:
    channel = PIPES["planar-pipe-4"].channel
    rng = np.random.default_rng(12)
    points = rng.uniform([0.0, -0.1], [0.45, 0.15], size=(40, 2))
    clearance, gradient = channel.clearance_and_gradient(points)
    h = 1e-7
    for axis in (0, 1):
        shifted = points.copy()
        shifted[:, axis] += h
        numeric = (channel.clearance(shifted) - clearance) / h
        # away from the openings (where the sign jumps by design) the clearance is smooth
        np.testing.assert_allclose(numeric, gradient[:, axis], atol=1e-5)


@pytest.mark.parametrize(
    ("walls", "reason"),
    [
        ((((0, 1), (1, 1)),) * 3, "3 walls"),
        ((tuple((0.01 * i, 1.0) for i in range(MAX_VERTICES + 1)), ((0, -1), (1, -1))), "17"),
        ((((0, 1), (1, -1)), ((0, -1), (1, 1))), "cross"),
        ((((0, 1), (0, 1), (1, 1)), ((0, -1), (1, -1))), "equal"),
    ],
)
def test_channels_the_environment_cannot_take_are_refused(walls: tuple, reason: str) -> None:
    with pytest.raises(ValueError, match=reason):
        Channel(walls, ((0.0, 0.0), (1.0, 0.0)))


def test_progress_is_arc_length_along_the_centreline() -> None:
    channel = PIPES["planar-pipe-4"].channel
    line = np.array(channel.centreline)
    stations = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))))
    np.testing.assert_allclose(channel.progress(line), stations, atol=1e-12)
    for s in (0.0, 0.1, 0.3, channel.length):
        point, tangent = channel.point_at(s)
        assert channel.progress(point[None])[0] == pytest.approx(s, abs=1e-12)
        assert np.linalg.norm(tangent) == pytest.approx(1.0)
    # beyond the ends the progress clamps; beside the line it is that of the foot point
    end, tangent = channel.point_at(channel.length)
    normal = np.array([-tangent[1], tangent[0]])
    beyond = np.array(
        [end + 0.05 * tangent, line[0] - [0.05, 0.0], end - 0.01 * tangent + 0.005 * normal]
    )
    np.testing.assert_allclose(
        channel.progress(beyond), [channel.length, 0.0, channel.length - 0.01], atol=1e-12
    )


def test_the_step_target_lies_a_lookahead_ahead_on_the_centreline() -> None:
    channel = PIPES["planar-pipe-4"].channel
    goal = np.array(PIPES["planar-pipe-4"].goal)
    goal_s = float(channel.progress(goal[None])[0])
    tip = channel.point_at(0.2)[0] + [0.0, 0.004]
    np.testing.assert_allclose(
        _target(channel, tip, goal, 0.2, goal_s, 0.02), channel.point_at(0.22)[0], atol=0
    )
    near = channel.point_at(goal_s - 0.01)[0]
    np.testing.assert_array_equal(_target(channel, near, goal, goal_s - 0.01, goal_s, 0.02), goal)


@pytest.mark.parametrize("name", sorted(PIPES))
def test_pipe_walls_are_parallel_to_the_centreline(name: str) -> None:
    """Past the mouth the walls are the centreline offset both ways: every centreline point,
    vertices included (the walls' miter joints), is equally far from both walls."""
    channel = PIPES[name].channel
    line = np.array(channel.centreline)
    pipe = line[line[:, 0] > 0.25 + 1e-9]
    pipe = pipe[channel.progress(pipe) < channel.length - 0.05]  # clear of the far opening
    dense = np.array([channel.point_at(s)[0] for s in np.linspace(0.26, 0.4, 57)])
    clearance = channel.clearance(np.vstack((pipe, dense)))
    np.testing.assert_allclose(clearance, clearance[0], atol=1e-9)


# ---------------------------------------------------------------------- the backbone


def test_sampled_backbone_and_its_jacobian_are_the_kinematics() -> None:
    lengths = np.array([0.06, 0.05, 0.06, 0.04, 0.06, 0.05])
    base = (0.01, -0.02, 0.3)
    rng = np.random.default_rng(3)
    for kappas in (np.zeros(6), rng.uniform(-20.0, 20.0, 6), np.array([1e-7, 20, -20, 0, 5, -1])):
        points, jacobian = sample_backbone(kappas, lengths, base, SAMPLES)
        reference = kinematics.backbone(kappas, lengths, base, SAMPLES)[1:, :2]
        np.testing.assert_allclose(points, reference, atol=1e-15)
        arcs = np.concatenate(
            [
                np.sum(lengths[:i]) + lengths[i] * np.arange(1, SAMPLES + 1) / SAMPLES
                for i in range(6)
            ]
        )
        for point, s in enumerate(arcs):
            expected = kinematics.point_jacobian(kappas, lengths, base, float(s))[:2]
            np.testing.assert_allclose(jacobian[point], expected, atol=1e-13)


# ---------------------------------------------------------------------- the pipe sections


@pytest.mark.parametrize("name", sorted(PIPES))
def test_pipe_sections_fit_the_environment_and_start_inside(name: str) -> None:
    section = PIPES[name]
    assert len(section.channel.walls) <= MAX_WALLS
    assert all(2 <= len(wall) <= MAX_VERTICES for wall in section.channel.walls)
    assert np.all(np.abs(section.start) <= KAPPA_LIMIT)
    points, _ = sample_backbone(section.start, section.lengths, section.base, SAMPLES)
    assert np.min(section.channel.clearance(points)) >= 0.5 * WIDTH + MARGIN
    goal = np.array([section.goal])
    assert section.channel.clearance(goal)[0] >= 0.5 * WIDTH + MARGIN
    # deep in the pipe: the goal lies 10 cm of centreline past the mouth (25 cm from the base),
    # at least 7 cm beyond the start's tip
    tip = kinematics.forward(section.start, section.lengths, section.base)[-1:, :2]
    assert section.channel.progress(goal)[0] == pytest.approx(0.35)
    assert section.channel.progress(goal)[0] - section.channel.progress(tip)[0] >= 0.07
    assert section.description


@pytest.mark.parametrize("name", sorted(PIPES))
def test_each_pipe_is_planned_to_its_goal_without_penetration(
    plans: dict[str, Plan], name: str
) -> None:
    section, plan = PIPES[name], plans[name]
    assert plan.reached, plan.reason
    assert plan.slack_steps == ()
    final = kinematics.forward(plan.configurations[-1], section.lengths, section.base)[-1, :2]
    assert np.linalg.norm(final - section.goal) <= 1e-3
    clearances = [
        np.min(section.channel.clearance(sample_backbone(k, section.lengths, section.base, 8)[0]))
        for k in plan.configurations
    ]
    assert min(clearances) >= 0.5 * WIDTH + MARGIN - 1e-7  # the margin holds at every waypoint
    assert plan.clearance_min == pytest.approx(min(clearances))
    assert plan_penetration(plan, WIDTH) == 0.0
    configurations = np.array(plan.configurations)
    assert np.all(configurations >= LOWER) and np.all(configurations <= UPPER)
    np.testing.assert_array_equal(configurations[0], section.start)
    # the trust region between consecutive waypoints
    assert np.max(np.abs(np.diff(configurations, axis=0))) <= STEP + 1e-12
    tips = np.array(
        [kinematics.forward(k, section.lengths, section.base)[-1, :2] for k in configurations]
    )
    np.testing.assert_allclose(plan.tip_path, tips, atol=0.0)
    # the tip advances along the channel, never back
    progress = section.channel.progress(tips)
    assert np.all(np.diff(progress) >= -1e-9), np.diff(progress)


@pytest.mark.parametrize("name", sorted(PIPES))
def test_curvature_moves_between_waypoints_keep_the_body_inside(
    plans: dict[str, Plan], name: str
) -> None:
    """What the controller does with the plan: one synchronised curvature move per waypoint,
    which interpolates the curvatures linearly; sampled finely, the body never penetrates."""
    section, plan = PIPES[name], plans[name]
    rates = np.full(6, 10.0)  # [1/(m s)]
    worst = math.inf
    for start, goal in zip(plan.configurations[:-1], plan.configurations[1:], strict=True):
        move = CurvatureMove.plan(start, goal, rates, accel_time=0.2)
        for tau in np.linspace(0.0, move.duration, 25):
            points, _ = sample_backbone(move.value(tau), section.lengths, section.base, 16)
            worst = min(worst, float(np.min(section.channel.clearance(points))))
    assert worst >= 0.5 * WIDTH


def test_large_steps_are_halved_until_the_move_between_waypoints_keeps_clear() -> None:
    """With a trust region of 8 1/m a waypoint's neighbours are far apart in curvature; the
    interpolation check halves the step until the body stays clear between them."""
    section = PIPES["planar-pipe-4"]
    plan = plan_pipe("planar-pipe-4", step=8.0, lookahead=0.08)
    assert plan.reached, plan.reason
    worst = math.inf
    for start, goal in zip(plan.configurations[:-1], plan.configurations[1:], strict=True):
        for f in np.linspace(0.0, 1.0, 21):
            kappa = start + f * (goal - start)
            points, _ = sample_backbone(kappa, section.lengths, section.base, SAMPLES)
            worst = min(worst, float(np.min(section.channel.clearance(points))))
    assert worst >= 0.5 * WIDTH


def test_the_planner_is_deterministic(plans: dict[str, Plan]) -> None:
    again = plan_pipe("planar-pipe-3")
    first = plans["planar-pipe-3"]
    assert len(again.configurations) == len(first.configurations)
    for a, b in zip(again.configurations, first.configurations, strict=True):
        np.testing.assert_array_equal(a, b)
    assert again.reason == first.reason


# ---------------------------------------------------------------------- failures are reports


def test_a_goal_outside_the_channel_is_a_reason_not_an_exception() -> None:
    section = PIPES["planar-pipe-1"]
    plan = plan_whole_arm(
        section.start, (0.35, 0.06), section.lengths, section.base, LOWER, UPPER, section.channel
    )
    assert not plan.reached
    assert "outside the channel" in plan.reason and "(0.3500, 0.0600)" in plan.reason
    assert len(plan.configurations) == 1


def test_a_goal_beyond_the_arms_reach_stalls_with_a_reason() -> None:
    section = PIPES["planar-pipe-1"]
    plan = plan_whole_arm(
        section.start, (0.40, 0.0), section.lengths, section.base, LOWER, UPPER, section.channel
    )
    assert not plan.reached
    assert "stalled" in plan.reason
    # it still got as far as it could: the tip near the straight arm's reach
    assert plan.tip_path[-1, 0] > 0.35


def test_infeasible_clearance_is_tolerated_with_slack_and_reported() -> None:
    """A margin of 13 mm asks for 21 mm of clearance where the 40 mm pipe leaves at most 20: the
    planner relaxes the clearance with a penalised slack, reports the steps, and still reaches
    the goal, as close to the demanded clearance as the pipe allows."""
    plan = plan_pipe("planar-pipe-4", margin=0.013)
    assert plan.slack_steps, plan.reason
    assert plan.reached, plan.reason
    assert 0.5 * WIDTH <= plan.clearance_min < 0.5 * WIDTH + 0.013


def test_inconsistent_inputs_are_errors() -> None:
    section = PIPES["planar-pipe-1"]
    args = (section.goal, section.lengths, section.base, LOWER, UPPER, section.channel)
    with pytest.raises(ValueError, match="start"):
        plan_whole_arm(np.zeros(5), *args)
    with pytest.raises(ValueError, match="outside"):
        plan_whole_arm(np.full(6, 25.0), *args)
