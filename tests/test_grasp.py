"""Grasp-and-place planning (robots/planar_arm/controller/grasp_planner.py, grasp_carry.py,
grasp_clearance.py) and the task draw (grasp.py): the approach waypoints on shrinking circles
facing the object, the grasp point on the object's centre, the object's clearance at every
waypoint and along every curvature interpolation (checked densely with kinematics.backbone and
gripper.finger_points, independently of the planner's vectorised bound), the carry along a
straight line, the retreat along the gripper's axis, the seeded task draw, and the errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controllers import kinematics
from robots.planar_arm.controller.grasp import DRAW_SHARE, START_MARGIN, draw_grasp_task
from robots.planar_arm.controller.grasp_carry import CARRY_STEP, plan_carry
from robots.planar_arm.controller.grasp_clearance import (
    SWEEP_TOLERANCE,
    _clearances,
    clearance,
    sweep_clearance,
    sweep_speed,
)
from robots.planar_arm.controller.grasp_planner import (
    HEADING_STEP,
    MARGIN,
    Arm,
    GraspPlan,
    default_radii,
    headings_around,
    plan_approach,
    plan_retreat,
)
from robots.planar_arm.controller.gripper import (
    GripperGeometry,
    finger_points,
    grasp_point,
    tip_for_grasp,
)
from robots.planar_arm.controller.ik import solve_ik

# the planar arm of planar-point-to-point.toml: six 0.06 m segments, base pointing up
LENGTHS = np.full(6, 0.06)
BASE = (0.0, 0.0, math.pi / 2)
# SegmentModel.reachable_curvature() of its segments is +-26.667 1/m (printed from
# PlanarArm().curvature_limits on that scenario); task_plan gives the IK IK_RANGE_SHARE = 0.9
LOWER, UPPER = np.full(6, -24.0), np.full(6, 24.0)
WIDTH = 0.02  # the rectangular segments' width: backbone capsules of radius 0.01 m
GEOMETRY = GripperGeometry()
RADIUS = 0.015  # [m] the thesis's objects are disks of 25-30 mm
START = np.zeros(6)
PLACE = (-0.1, 0.25)

# object centre, radius, start configuration, radii
CASES = {
    "right": ((0.12, 0.2), RADIUS, START, None),
    # a wide object and one radial move: the move's interpolation swings the fingers into the
    # object, so the planner must split it on the radial line
    "split": (
        (0.15737610658522697, 0.3394767165191674),
        0.0175,
        np.array([-4.164083221722851, 0.5500364110845144, 7.63912463842145,
                  11.784364242927843, -10.049406391387713, 12.48247849845394]),
        (0.07, 0.0),
    ),
    # the object beside the arm's body: the moves onto the outer circle of the headings with
    # the least motion sweep the body through it, so the plan must take another heading
    "beside": (
        (0.19486574104952406, 0.1959820183500471),
        RADIUS,
        np.array([-10.687678941051452, -12.10476548139797, 17.43963003573171,
                  -6.127198940006204, -2.2504512376529853, 5.993754306985107]),
        None,
    ),
}  # fmt: skip


def approach(name: str) -> GraspPlan:
    centre, radius, start, radii = CASES[name]
    return plan_approach(
        centre, radius, start, LENGTHS, BASE, LOWER, UPPER, GEOMETRY, radii=radii, width=WIDTH
    )


@pytest.fixture(scope="module")
def approaches() -> dict[str, GraspPlan]:
    return {name: approach(name) for name in CASES}


@pytest.fixture(scope="module")
def carry(approaches: dict[str, GraspPlan]) -> GraspPlan:
    grasp = approaches["right"].waypoints[-1]
    return plan_carry(
        PLACE,
        grasp[0],
        grasp[1][2],
        LENGTHS,
        BASE,
        LOWER,
        UPPER,
        GEOMETRY,
        object_radius=RADIUS,
        width=WIDTH,
    )


def dense_clearance(kappas: np.ndarray, centre: tuple[float, float], radius: float) -> float:
    """Clearance of the object from the backbone capsules and the open fingers, from points
    sampled on the true arcs (so never below the true clearance)."""
    spine = kinematics.backbone(kappas, LENGTHS, BASE, per_segment=32)
    body = float(np.min(np.linalg.norm(spine[:, :2] - centre, axis=1))) - WIDTH / 2
    fingers = finger_points(GEOMETRY, tuple(spine[-1]), GEOMETRY.theta_open, samples=32)
    nearest = min(float(np.min(np.linalg.norm(f - centre, axis=1))) for f in fingers)
    return min(body, nearest - GEOMETRY.finger_width / 2) - radius


def plan_clearance(plan: GraspPlan, radius: float, per_move: int = 41) -> float:
    """Dense clearance over the plan: its start, every waypoint and the straight curvature
    interpolation of every move, the first one from the start included."""
    chain = [plan.start] + [k for k, _ in plan.waypoints]
    values = []
    for a, b in zip(chain[:-1], chain[1:], strict=True):
        for s in np.linspace(0.0, 1.0, per_move):
            values.append(dense_clearance(a + s * (b - a), plan.centre, radius))
    return min(values)


def tip(kappas: np.ndarray) -> np.ndarray:
    return kinematics.forward(kappas, LENGTHS, BASE)[-1]


# ---------------------------------------------------------------------- clearance bounds


def test_clearance_is_a_tight_lower_bound_of_the_dense_geometry() -> None:
    rng = np.random.default_rng(4)
    for _ in range(20):
        kappas = rng.uniform(LOWER, UPPER)
        centre = tuple(rng.uniform((-0.3, -0.1), (0.3, 0.4)))
        bound = clearance(
            kappas, centre, RADIUS, LENGTHS, BASE, GEOMETRY, GEOMETRY.theta_open, width=WIDTH
        )
        dense = dense_clearance(kappas, centre, RADIUS)
        assert dense - 1e-4 <= bound <= dense + 1e-12


def test_sweep_clearance_bounds_the_whole_interpolation() -> None:
    # the static bound is checked above against the dense geometry; here the sweep's bound
    # against the static bound on an interpolation sampled far finer than the sweep samples it
    rng = np.random.default_rng(5)
    for _ in range(3):
        a, b = rng.uniform(LOWER / 4, UPPER / 4, size=(2, 6))
        # an object 5 mm beside the body halfway through the move, on a random side
        spine = kinematics.backbone(0.5 * (a + b), LENGTHS, BASE, per_segment=8)
        x, y, heading = spine[rng.integers(8, len(spine))]
        side = (WIDTH / 2 + RADIUS + 0.005) * rng.choice((-1.0, 1.0))
        centre = (x - side * math.sin(heading), y + side * math.cos(heading))
        fractions = np.linspace(0.0, 1.0, 6001)
        fine = min(
            float(
                np.min(
                    _clearances(
                        a + s[:, None] * (b - a),
                        centre,
                        RADIUS,
                        LENGTHS,
                        BASE,
                        GEOMETRY,
                        GEOMETRY.theta_open,
                        WIDTH,
                    )
                )
            )
            for s in np.array_split(fractions, 4)
        )
        bound = sweep_clearance(
            a, b, centre, RADIUS, LENGTHS, BASE, GEOMETRY, GEOMETRY.theta_open, width=WIDTH
        )
        assert fine - SWEEP_TOLERANCE <= bound <= fine


def test_sweep_speed_bounds_every_point_and_is_near_tight_for_one_bend() -> None:
    def body(kappas: np.ndarray) -> np.ndarray:
        spine = kinematics.backbone(kappas, LENGTHS, BASE, per_segment=16)
        fingers = finger_points(GEOMETRY, tuple(spine[-1]), GEOMETRY.theta_open, samples=16)
        return np.vstack((spine[:, :2], *fingers))

    def fastest(a: np.ndarray, b: np.ndarray) -> float:
        d = 1e-5
        return max(
            float(
                np.max(np.linalg.norm(body(a + (s + d) * (b - a)) - body(a + s * (b - a)), axis=1))
            )
            / d
            for s in np.linspace(0.0, 1.0 - 1e-5, 51)
        )

    rng = np.random.default_rng(9)
    for _ in range(4):
        a, b = rng.uniform(LOWER, UPPER, size=(2, 6))
        assert fastest(a, b) <= sweep_speed(a, b, LENGTHS, GEOMETRY) * (1.0 + 1e-6)
    # the first segment alone, from straight: everything turns about the base
    bend = np.zeros(6)
    bend[0] = 10.0
    speed = sweep_speed(np.zeros(6), bend, LENGTHS, GEOMETRY)
    assert 0.8 * speed <= fastest(np.zeros(6), bend) <= speed


def test_ring_continues_round_the_circle_both_ways() -> None:
    arm = Arm.of(LENGTHS, BASE, LOWER, UPPER, GEOMETRY, WIDTH)
    centre, standoff = (0.12, 0.2), 0.04
    seed = arm.seed(centre, standoff, START)
    assert seed is not None
    ring = list(headings_around(arm, centre, standoff, float(tip(seed)[2]), seed))
    steps = [j for j, _, _ in ring]
    assert min(steps) <= -2 and max(steps) >= 2 and len(set(steps)) == len(steps)
    for j, heading, kappas in ring:
        assert heading == pytest.approx(ring[0][1] + j * HEADING_STEP)
        pose = tip_for_grasp(GEOMETRY, centre, heading, standoff)
        assert np.allclose(tip(kappas)[:2], pose[:2], atol=1e-6)
        assert math.remainder(tip(kappas)[2] - heading, 2 * math.pi) == pytest.approx(0, abs=1e-6)


# ---------------------------------------------------------------------- approach


@pytest.mark.parametrize("name", list(CASES))
def test_approach_waypoints_lie_on_shrinking_circles_facing_the_centre(
    approaches: dict[str, GraspPlan], name: str
) -> None:
    plan = approaches[name]
    centre_, radius, _, given = CASES[name]
    centre = np.array(centre_)
    radii = default_radii(radius, GEOMETRY) if given is None else given
    assert plan.radii == tuple(radii)
    assert set(radii) <= set(plan.standoffs)  # every circle is visited
    assert plan.standoffs[0] == radii[0] and plan.standoffs[-1] == 0.0
    assert all(b < a for a, b in zip(plan.standoffs, plan.standoffs[1:], strict=False))
    assert len(plan.standoffs) == len(plan.waypoints)
    for (kappas, pose), standoff in zip(plan.waypoints, plan.standoffs, strict=True):
        actual = tip(kappas)
        assert np.all(kappas >= LOWER) and np.all(kappas <= UPPER)
        assert np.allclose(actual[:2], pose[:2], atol=1e-6)
        assert abs(actual[2] - pose[2]) < 1e-6  # the heading on the configuration's branch
        ahead = centre - actual[:2]
        assert np.linalg.norm(ahead) == pytest.approx(GEOMETRY.grasp_offset + standoff, abs=2e-6)
        facing = np.array([math.cos(actual[2]), math.sin(actual[2])])
        assert float(facing @ ahead) / np.linalg.norm(ahead) > 1.0 - 1e-9
        # radially inwards at one heading, the plan's
        assert math.remainder(actual[2] - plan.heading, 2 * math.pi) == pytest.approx(0, abs=2e-6)


@pytest.mark.parametrize("name", list(CASES))
def test_approach_ends_with_the_grasp_point_on_the_centre(
    approaches: dict[str, GraspPlan], name: str
) -> None:
    last = approaches[name].waypoints[-1][0]
    point = grasp_point(GEOMETRY, tuple(tip(last)))
    assert np.linalg.norm(point - np.array(CASES[name][0])) < 5e-4


@pytest.mark.parametrize("name", list(CASES))
def test_approach_keeps_the_margin_at_waypoints_and_between_them(
    approaches: dict[str, GraspPlan], name: str
) -> None:
    plan = approaches[name]
    dense = plan_clearance(plan, CASES[name][1])
    assert dense >= MARGIN
    assert MARGIN <= plan.clearance <= dense + 1e-12  # the plan's figure is a lower bound


def test_a_move_that_would_touch_is_split_on_its_radial_line(
    approaches: dict[str, GraspPlan],
) -> None:
    plan = approaches["split"]
    assert len(plan.waypoints) > len(plan.radii)
    # the same move unsplit does touch the object (else the case tests nothing)
    outer, grasp = plan.waypoints[0][0], plan.waypoints[-1][0]
    assert (
        plan_clearance(
            GraspPlan(outer, ((grasp, (0.0, 0.0, 0.0)),), 0.0, (), plan.centre, (0.0,), 0.0), 0.0175
        )
        < MARGIN
    )


def test_approach_configurations_vary_continuously(approaches: dict[str, GraspPlan]) -> None:
    for plan in approaches.values():
        steps = np.abs(np.diff(plan.kappas, axis=0))
        # warm-started from its neighbour, no waypoint jumps to another IK branch
        assert float(np.max(steps, initial=0.0)) < 0.25 * float(np.min(UPPER - LOWER))


def test_approach_heading_has_the_least_motion_of_its_neighbours(
    approaches: dict[str, GraspPlan],
) -> None:
    plan = approaches["right"]
    centre, radius, start, _ = CASES["right"]
    radii = default_radii(radius, GEOMETRY)
    grasp = plan.waypoints[-1][0]
    for offset in (-2, -1, 1, 2):
        heading = plan.heading + offset * HEADING_STEP
        kappas = solve_ik(
            tip_for_grasp(GEOMETRY, centre, heading)[:2],
            grasp,
            LENGTHS,
            BASE,
            LOWER,
            UPPER,
            heading=heading,
        )
        if not kappas.converged:
            continue
        chain = [kappas.kappas]
        for standoff in radii[-2::-1]:
            result = solve_ik(
                tip_for_grasp(GEOMETRY, centre, heading, standoff)[:2],
                chain[-1],
                LENGTHS,
                BASE,
                LOWER,
                UPPER,
                heading=heading,
            )
            assert result.converged
            chain.append(result.kappas)
        moves = np.diff(np.vstack([start] + chain[::-1]), axis=0)
        assert plan.motion() <= float(np.sum(np.max(np.abs(moves), axis=1))) + 1e-6


# ---------------------------------------------------------------------- carry and retreat


def test_carry_moves_the_grasp_point_along_the_line_to_the_place(
    approaches: dict[str, GraspPlan], carry: GraspPlan
) -> None:
    grasp = approaches["right"].waypoints[-1]
    origin = grasp_point(GEOMETRY, tuple(tip(grasp[0])))
    place = np.array(PLACE)
    line = (place - origin) / np.linalg.norm(place - origin)
    points = [origin]
    headings = [grasp[1][2]]
    for kappas, pose in carry.waypoints:
        actual = tip(kappas)
        assert np.allclose(actual[:2], pose[:2], atol=1e-6)
        point = grasp_point(GEOMETRY, tuple(actual))
        off = point - origin
        assert abs(off[0] * line[1] - off[1] * line[0]) < 1e-5  # on the line
        points.append(point)
        headings.append(float(actual[2]))
    progress = [float((p - origin) @ line) for p in points]
    assert all(b > a for a, b in zip(progress, progress[1:], strict=False))
    assert float(np.max(np.diff(progress))) <= CARRY_STEP + 1e-5
    assert np.max(np.abs(np.diff(headings))) <= HEADING_STEP + 1e-5
    assert np.linalg.norm(points[-1] - place) < 5e-4
    assert math.remainder(headings[-1] - carry.heading, 2 * math.pi) == pytest.approx(0, abs=1e-5)


def test_carry_turns_only_as_far_as_the_place_needs(
    approaches: dict[str, GraspPlan], carry: GraspPlan
) -> None:
    grasp = approaches["right"].waypoints[-1]
    free = plan_carry(PLACE, grasp[0], grasp[1][2], LENGTHS, BASE, LOWER, UPPER, GEOMETRY)
    kappas, pose = free.waypoints[-1]
    turn = pose[2] - grasp[1][2]
    # the grid heading next nearer to the grasp heading is out of reach at the place
    nearer = pose[2] - math.copysign(HEADING_STEP, turn)
    assert abs(nearer - grasp[1][2]) < abs(turn)
    target = tip_for_grasp(GEOMETRY, PLACE, nearer)
    assert not solve_ik(target[:2], kappas, LENGTHS, BASE, LOWER, UPPER, heading=nearer).converged
    # asked to leave room for the retreat, the carry turns further: from the nearest heading
    # the gripper cannot back off
    assert abs(carry.heading - grasp[1][2]) > abs(turn)
    with pytest.raises(ValueError, match="is unreachable"):
        plan_retreat(PLACE, RADIUS, kappas, pose[2], LENGTHS, BASE, LOWER, UPPER, GEOMETRY)


def test_carry_keeps_the_heading_where_the_place_allows(approaches: dict[str, GraspPlan]) -> None:
    grasp = approaches["right"].waypoints[-1]
    heading = grasp[1][2]
    nearby = tuple(grasp_point(GEOMETRY, tuple(tip(grasp[0]))) + (-0.03, 0.01))
    plan = plan_carry(nearby, grasp[0], heading, LENGTHS, BASE, LOWER, UPPER, GEOMETRY)
    for kappas, _ in plan.waypoints:
        assert math.remainder(tip(kappas)[2] - heading, 2 * math.pi) == pytest.approx(0, abs=1e-5)


def test_retreat_backs_off_along_the_axis_without_touching(carry: GraspPlan) -> None:
    release, pose = carry.waypoints[-1]
    plan = plan_retreat(
        PLACE, RADIUS, release, pose[2], LENGTHS, BASE, LOWER, UPPER, GEOMETRY, width=WIDTH
    )
    outer = default_radii(RADIUS, GEOMETRY)[0]
    assert plan.radii == default_radii(RADIUS, GEOMETRY)[::-1]
    assert set(plan.radii[1:]) <= set(plan.standoffs) and plan.standoffs[-1] == outer
    assert all(b > a for a, b in zip((0.0,) + plan.standoffs, plan.standoffs, strict=False))
    for kappas, standoff in zip(plan.kappas, plan.standoffs, strict=True):
        actual = tip(kappas)
        assert np.allclose(actual[:2], tip_for_grasp(GEOMETRY, PLACE, pose[2], standoff)[:2])
        assert math.remainder(actual[2] - pose[2], 2 * math.pi) == pytest.approx(0, abs=1e-5)
    assert plan_clearance(plan, RADIUS) >= MARGIN <= plan.clearance


def test_retreat_poses_take_the_configurations_heading_branch(carry: GraspPlan) -> None:
    release, pose = carry.waypoints[-1]
    plans = [
        plan_retreat(PLACE, RADIUS, release, heading, LENGTHS, BASE, LOWER, UPPER, GEOMETRY)
        for heading in (pose[2], pose[2] + 2 * math.pi)
    ]
    assert np.allclose(plans[0].kappas, plans[1].kappas)
    for plan in plans:
        assert np.allclose(plan.poses, [tip(k) for k in plan.kappas], atol=1e-6)


# ---------------------------------------------------------------------- task draw


def draw(seed: int, **options: object) -> tuple[tuple[float, float], tuple[float, float]]:
    return draw_grasp_task(
        np.random.default_rng(seed),
        LENGTHS,
        BASE,
        LOWER,
        UPPER,
        GEOMETRY,
        RADIUS,
        START,
        width=WIDTH,
        **options,  # type: ignore[arg-type]
    )


def reaches_grasp_pose(point: tuple[float, float], lower: np.ndarray, upper: np.ndarray) -> bool:
    """Some heading (15 degree grid, the bearing from the base first) at which the grasp pose
    on `point` is met by heading-constrained IK from the start within the bounds."""
    bearing = math.atan2(point[1] - BASE[1], point[0] - BASE[0])
    for k in sorted(range(-12, 12), key=abs):
        heading = bearing + k * math.pi / 12
        pose = tip_for_grasp(GEOMETRY, point, heading)
        if solve_ik(pose[:2], START, LENGTHS, BASE, lower, upper, heading=heading).converged:
            return True
    return False


def test_draw_is_seeded() -> None:
    assert draw(3, plannable=False) == draw(3, plannable=False)
    assert draw(4, plannable=False) != draw(3, plannable=False)


def test_a_plannable_draw_is_one_the_planner_accepts() -> None:
    # a margin the open gripper cannot keep: every plan fails, so no draw is plannable
    assert draw(3, margin=0.01, plannable=False)
    with pytest.raises(ValueError, match="no object and place found in 3 draws"):
        draw(3, margin=0.01, attempts=3)


@pytest.mark.parametrize("seed", [3, 8])
def test_drawn_objects_and_places_are_graspable_and_apart(seed: int) -> None:
    centre, place = draw(seed, plannable=False)
    shrink = 0.5 * (UPPER - LOWER) * DRAW_SHARE
    assert reaches_grasp_pose(centre, -shrink, shrink)
    assert reaches_grasp_pose(place, -shrink, shrink)
    assert math.dist(centre, place) >= 0.06
    assert dense_clearance(START, centre, RADIUS) >= START_MARGIN


@pytest.mark.parametrize("seed", [0, 1])
def test_drawn_objects_keep_the_start_margin_from_the_arm(seed: int) -> None:
    # drawn with no margin these seeds put the object 0.16 to 0.18 m from the straight arm
    centre, _ = draw(seed, start_margin=0.2, plannable=False)
    assert dense_clearance(START, centre, RADIUS) >= 0.2


def test_a_drawn_task_leaves_the_controller_room_to_plan(monkeypatch: pytest.MonkeyPatch) -> None:
    """The controller plans again from estimates: a kept draw's plans keep DRAW_SLACK beyond
    the margin, and its approach is plannable from the start shaken by START_SHAKE both ways."""
    import robots.planar_arm.controller.grasp as grasp

    calls: list[tuple[float, np.ndarray]] = []
    original = grasp.plan_approach  # the planner's, as the draw calls it

    def spy(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append((kwargs["margin"], np.asarray(args[2], float)))
        return original(*args, **kwargs)

    monkeypatch.setattr(grasp, "plan_approach", spy)
    draw(3)
    kept = calls[-3:]  # the draw that was kept: its three approaches, in order
    pattern = np.where(np.arange(START.size) % 2 == 0, 1.0, -1.0) * grasp.START_SHAKE
    assert kept[0][0] == pytest.approx(MARGIN + grasp.DRAW_SLACK)
    assert np.array_equal(kept[0][1], START)
    assert [m for m, _ in kept[1:]] == [MARGIN, MARGIN]
    assert kept[1][1] == pytest.approx(START + pattern)
    assert kept[2][1] == pytest.approx(START - pattern)
    assert grasp.DRAW_SLACK > 0 and grasp.START_SHAKE > 0


def test_draw_gives_up_after_its_attempts() -> None:
    with pytest.raises(ValueError, match="no object and place found in 5 draws"):
        draw(1, separation=1.0, attempts=5, plannable=False)


# ---------------------------------------------------------------------- errors


def test_an_object_beyond_reach_raises() -> None:
    with pytest.raises(ValueError, match=r"object at \(0.4000, 0.3000\) m is beyond"):
        plan_approach((0.4, 0.3), RADIUS, START, LENGTHS, BASE, LOWER, UPPER, GEOMETRY)


def test_an_object_the_bounds_do_not_reach_raises() -> None:
    stiff = np.full(6, 2.0)  # bends at most 0.12 rad per segment: a narrow fan ahead
    with pytest.raises(ValueError, match=r"no grasp pose reaches the object at \(0.2000"):
        plan_approach((0.2, 0.1), RADIUS, START, LENGTHS, BASE, -stiff, stiff, GEOMETRY)


def test_an_object_touching_the_arm_now_raises() -> None:
    with pytest.raises(ValueError, match="from the arm in its current configuration"):
        plan_approach((0.02, 0.15), RADIUS, START, LENGTHS, BASE, LOWER, UPPER, GEOMETRY)


def test_an_object_wider_than_the_open_gripper_raises() -> None:
    with pytest.raises(ValueError, match="does not fit the open gripper"):
        plan_approach((0.12, 0.2), 0.02, START, LENGTHS, BASE, LOWER, UPPER, GEOMETRY)


@pytest.mark.parametrize("radii", [(0.05, 0.02), (0.02, 0.05, 0.0), (0.05,)])
def test_approach_radii_must_shrink_to_zero(radii: tuple[float, ...]) -> None:
    with pytest.raises(ValueError, match="radii"):
        plan_approach(
            (0.12, 0.2), RADIUS, START, LENGTHS, BASE, LOWER, UPPER, GEOMETRY, radii=radii
        )
