"""Collision-free free-space moves (OMPL RRTConnect over pybullet distance queries)."""

from __future__ import annotations

import itertools

import numpy as np
import pybullet as p
import pytest

from parcelpick_env.robot.arm import Gen3Arm
from parcelpick_env.robot.planning import (
    HELD_LINK,
    Attachment,
    MotionPlanner,
    PlannerConfig,
)
from parcelpick_env.robot.timing import GEN3_LIMITS, joint_trajectory

DOWN = np.array([0.0, 0.0, -1.0])


@pytest.fixture()
def world():
    c = p.connect(p.DIRECT)
    p.setGravity(0, 0, -9.81, physicsClientId=c)
    arm = Gen3Arm(c)
    seed = np.asarray(arm.config.ik_seed)
    q_a = arm.ik([-0.3, 0.05, 0.2], DOWN, seed=seed)
    q_b = arm.ik([0.3, 0.05, 0.2], DOWN, seed=q_a)
    assert q_a is not None and q_b is not None
    yield c, arm, q_a, q_b
    p.disconnect(c)


def box(client, half, centre, mass=0.0):
    col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=client)
    return p.createMultiBody(mass, col, basePosition=centre, physicsClientId=client)


def min_distance(client, arm_body, body, path, resolution=0.002):
    """Smallest arm-to-body distance over the joint polyline, sampled every ``resolution`` rad."""
    best = np.inf
    for a, b in itertools.pairwise(path):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / resolution)))
        for u in np.linspace(0.0, 1.0, n + 1):
            q = a + u * (b - a)
            for j, v in zip(range(7), q):
                p.resetJointState(arm_body, int(j), float(v), physicsClientId=client)
            pts = p.getClosestPoints(arm_body, body, 0.05, physicsClientId=client)
            best = min([best] + [cp[8] for cp in pts])
    return best


def test_a_planned_move_around_a_tall_stack_never_touches_it(world):
    c, arm, q_a, q_b = world
    stack = box(c, [0.06, 0.06, 0.3], [0.0, 0.05, 0.3])  # a 60 cm column of parcels between start and goal
    planner = arm.planner
    hit = planner.segment_collision(q_a, q_b)
    assert hit is not None and hit.body == stack  # the straight move would hit it
    path = planner.plan(q_a, q_b)
    assert path is not None, planner.last_failure
    assert planner.stats.method == "rrt"
    np.testing.assert_array_equal(path[0], q_a)
    np.testing.assert_array_equal(path[-1], q_b)
    for q in path:
        assert np.all(q >= arm.lower) and np.all(q <= arm.upper)
    # checked far more densely than the planner did, the whole path keeps clear of the stack
    assert min_distance(c, arm.body, stack, path) > 0.0
    # the timed trajectory of the plan (what the arm executes) is clear too, sample by sample
    arm.set_joints(q_a)
    traj = joint_trajectory(q_a, path[1:], GEN3_LIMITS, 1.0 / 240.0)
    res = arm.sweep_trajectory(traj)
    assert res.completed and res.collision is None
    np.testing.assert_allclose(arm.q, q_b)


def test_plans_are_deterministic_under_the_seed(world):
    c, arm, q_a, q_b = world
    box(c, [0.06, 0.06, 0.3], [0.0, 0.05, 0.3])
    first = MotionPlanner(arm, c, PlannerConfig(seed=7)).plan(q_a, q_b)
    other = MotionPlanner(arm, c, PlannerConfig(seed=3)).plan(q_a, q_b)  # an RNG draw in between
    again = MotionPlanner(arm, c, PlannerConfig(seed=7)).plan(q_a, q_b)
    assert first is not None and other is not None and again is not None
    assert len(first) == len(again)
    for x, y in zip(first, again):
        np.testing.assert_array_equal(x, y)


def test_a_loaded_machine_plans_the_same_path(world, monkeypatch):
    """The search budget is state checks, not seconds: slowing every check (a busy machine) changes nothing."""
    import time

    c, arm, q_a, q_b = world
    box(c, [0.06, 0.06, 0.3], [0.0, 0.05, 0.3])
    quick = MotionPlanner(arm, c, PlannerConfig(seed=7, retries=0))
    fast = quick.plan(q_a, q_b)
    checks = quick.stats.checks
    slow = MotionPlanner(arm, c, PlannerConfig(seed=7, retries=0))
    original = slow._check
    monkeypatch.setattr(slow, "_check", lambda *a, **k: (time.sleep(0.0005), original(*a, **k))[1])
    loaded = slow.plan(q_a, q_b)
    assert fast is not None and loaded is not None and slow.stats.checks == checks
    for x, y in zip(fast, loaded, strict=True):
        np.testing.assert_array_equal(x, y)
    tiny = MotionPlanner(arm, c, PlannerConfig(seed=7, retries=0, check_budget=5))
    assert tiny.plan(q_a, q_b) is None and "within 5 state checks" in tiny.last_failure


def test_a_clear_move_takes_the_straight_fast_path(world):
    _c, arm, q_a, q_b = world
    path = arm.planner.plan(q_a, q_b)
    assert arm.planner.stats.method == "straight" and len(path) == 2
    np.testing.assert_array_equal(path[1], q_b)


def test_start_or_goal_in_collision_is_refused_with_a_reason(world):
    c, arm, q_a, q_b = world
    arm.set_joints(q_b)
    tip = arm.kin.forward(q_b)[0]
    wall = box(c, [0.05, 0.05, 0.05], tip + [0, 0, 0.06])  # around the tool at the goal
    assert arm.planner.plan(q_a, q_b) is None
    assert "goal in collision" in arm.planner.last_failure and str(wall) in arm.planner.last_failure


def test_a_held_parcel_is_checked_and_avoided(world):
    c, arm, q_a, q_b = world
    arm.set_joints(q_a)
    tip = arm.kin.forward(q_a)[0]
    parcel = box(c, [0.05, 0.05, 0.12], tip + [0, 0, -0.125], mass=1.0)  # hangs 25 cm below the cup
    held = Attachment.current(arm, parcel)
    np.testing.assert_allclose(held.tool_T_body[:3, 3], [0, 0, 0.125], atol=1e-3)  # along the approach axis
    # a low wall between start and goal: the bare arm passes over it, the parcel hanging below does not
    wall = box(c, [0.02, 0.3, 0.04], [0.0, 0.05, 0.04])
    q_mid = 0.5 * (q_a + q_b)
    assert arm.planner.collision(q_mid) is None
    hit = arm.planner.collision(q_mid, attached=held)
    assert hit is not None and hit.link == HELD_LINK and hit.body == wall
    # queries leave the arm and the parcel where they were
    np.testing.assert_allclose(arm.q, q_a)
    np.testing.assert_allclose(p.getBasePositionAndOrientation(parcel, physicsClientId=c)[0], tip + [0, 0, -0.125],
                               atol=1e-9)
    path = arm.planner.plan(q_a, q_b, attached=held)
    assert path is not None, arm.planner.last_failure
    assert arm.planner.stats.method == "rrt"
    assert arm.planner.path_collision(path, attached=held, margin=0.0) is None
    traj = joint_trajectory(q_a, path[1:], GEN3_LIMITS, 1.0 / 60.0)
    assert arm.sweep_trajectory(traj, attached=held).completed


def test_self_collision_of_a_folded_arm_is_found(world):
    """Beside its pedestal only the arm itself can collide: some random folds put the wrist or tool into
    the base or upper arm, and the check names both links."""
    c, arm, _, _ = world
    rng = np.random.default_rng(0)
    bare = MotionPlanner(arm, c, PlannerConfig(self_collision=False))
    hits = []
    for _ in range(300):
        q = rng.uniform(arm.lower, arm.upper)
        hit = arm.planner.collision(q)
        if hit is not None and hit.body == arm.body:
            hits.append(hit)
            assert "(self: " in hit.link and hit.distance < 0
            assert bare.collision(q) is None or bare.collision(q).body == arm.pedestal
    assert 0 < len(hits) < 60
    assert arm.planner.collision(np.asarray(arm.config.home)) is None  # the tucked home pose is clear


def test_a_goal_just_above_a_parcel_plans_with_the_clearance_it_has(world):
    """A pre-grasp pose 4 mm above a parcel is inside the 1 cm margin but touches nothing: the plan
    is made with half the goal's clearance instead of being refused."""
    c, arm, q_a, q_b = world
    tip = arm.kin.forward(q_b)[0]
    parcel = box(c, [0.05, 0.05, 0.05], tip - [0, 0, 0.054])  # top 4 mm below the cup lip
    path = arm.planner.plan(q_a, q_b)
    assert path is not None, arm.planner.last_failure
    assert 0.0 < arm.planner.stats.extra["margin"] <= 0.0021
    assert arm.planner.path_collision(path, margin=0.0) is None
    assert arm.planner.collision(q_b).body == parcel  # within the configured margin, as said


def test_a_start_a_hair_past_a_joint_limit_still_plans(world):
    """The motors can leave a joint microradians past its limit after a driven move; the next free move plans
    from the clipped state instead of refusing it (it used to end a whole clearance run)."""
    c, arm, q_a, q_b = world
    past = q_a.copy()
    past[6] = arm.upper[6] + 5e-6
    arm.set_joints(past)
    goal = q_b.copy()
    goal[6] = arm.upper[6] - 0.5
    traj, why = arm.free_trajectory(goal, 1.0 / 240.0)
    assert traj is not None, why
    assert np.all(traj.q >= arm.lower - 1e-9) and np.all(traj.q <= arm.upper + 1e-9)
    np.testing.assert_allclose(traj.q[0], np.clip(past, arm.lower, arm.upper))
    np.testing.assert_allclose(traj.q[-1], goal)
