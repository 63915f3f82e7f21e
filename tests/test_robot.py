"""The Gen3 URDF, its kinematics, verified IK, driven and kinematic execution of timed trajectories."""

from __future__ import annotations

import math

import numpy as np
import pybullet as p
import pytest
from scipy.spatial.transform import Rotation

from parcelpick_env.robot.arm import ArmConfig, Gen3Arm, reachability
from parcelpick_env.robot.gen3 import (
    JOINTS,
    URDF_PATH,
    VELOCITY_LIMIT,
    SuctionToolSpec,
    gen3_suction_urdf,
)
from parcelpick_env.robot.kinematics import Gen3Kinematics, cross_rows
from parcelpick_env.robot.timing import GEN3_LIMITS, bound_violation, joint_trajectory


@pytest.fixture()
def client():
    c = p.connect(p.DIRECT)
    yield c
    p.disconnect(c)


def test_committed_urdf_matches_the_writer():
    assert URDF_PATH.read_text() == gen3_suction_urdf()


def test_zero_configuration_matches_kinova_figures(client):
    arm = Gen3Arm(client, ArmConfig(base_position=(0.0, 0.0, 0.0), base_yaw=0.0))
    arm.set_joints(np.zeros(7))
    names = [p.getJointInfo(arm.body, j, physicsClientId=client)[12].decode() for j in range(p.getNumJoints(arm.body, physicsClientId=client))]
    ee = p.getLinkState(arm.body, names.index("end_effector_link"), computeForwardKinematics=True, physicsClientId=client)
    assert ee[4][2] == pytest.approx(1.1874, abs=1e-3)
    tip, _ = arm.tip_pose()
    assert tip[2] == pytest.approx(1.1874 + SuctionToolSpec().length, abs=1e-3)  # tool points straight up
    # limits and velocity as published (V12)
    infos = [p.getJointInfo(arm.body, int(j), physicsClientId=client) for j in arm.joints]
    assert [round(i[9], 2) for i in infos][1::2] == [2.41, 2.66, 2.23]
    assert all(i[11] == pytest.approx(VELOCITY_LIMIT) for i in infos)
    assert len(arm.joints) == len(JOINTS) == 7


def test_kinematics_agree_with_pybullet(client):
    arm = Gen3Arm(client)
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = rng.uniform(arm.lower, arm.upper)
        arm.set_joints(q)
        pos, quat = arm.tip_pose()
        tip, axis, _, _ = arm.kin.forward(q)
        np.testing.assert_allclose(tip, pos, atol=1e-5)
        np.testing.assert_allclose(axis, Rotation.from_quat(quat).as_matrix()[:, 2], atol=1e-5)
        position, R = arm.kin.tool_pose(q)  # the whole tool frame, yaw included
        np.testing.assert_allclose(position, pos, atol=1e-5)
        np.testing.assert_allclose(R, Rotation.from_quat(quat).as_matrix(), atol=5e-5)  # pybullet: float32
        np.testing.assert_allclose(arm.kin.tips(q[None])[0], pos, atol=1e-5)  # batched


def test_kinematics_answers_are_the_callers_own_not_views_of_pinocchios_data():
    """pinocchio hands out its placements as views; an answer kept by a caller (the IK's tip, the hold check's
    tool state) must not change when the next configuration is computed."""
    kin = Gen3Kinematics(ArmConfig().base_position, ArmConfig().base_yaw, 0.12)
    rng = np.random.default_rng(4)
    q1, q2 = rng.uniform(-1.0, 1.0, (2, 7))
    calls = [lambda q: kin.forward(q), lambda q: kin.tool_pose(q), lambda q: (kin.tip_x(q),),
             lambda q: kin.jacobian(q), lambda q: kin.tool_motion(q, np.ones(7), np.ones(7)),
             lambda q: (kin.tips(q[None]),)]
    for call in calls:
        kept = call(q1)
        copies = [np.array(x, copy=True) for x in kept]
        call(q2)
        for x, y in zip(kept, copies):
            np.testing.assert_array_equal(x, y)


def test_ik_is_verified_and_within_limits(client):
    arm = Gen3Arm(client)
    seed = np.asarray(arm.config.ik_seed)
    target, axis = np.array([0.1, 0.05, 0.15]), np.array([0.0, 0.0, -1.0])
    q = arm.ik(target, axis, seed=seed)
    assert q is not None
    assert np.all(q >= arm.lower - 1e-9) and np.all(q <= arm.upper + 1e-9)
    before = arm.q.copy()
    arm.set_joints(q)
    pos, quat = arm.tip_pose()
    assert np.linalg.norm(pos - target) < arm.config.ik_position_tol
    assert Rotation.from_quat(quat).as_matrix()[:, 2] @ axis > math.cos(arm.config.ik_angle_tol)
    # ik leaves the arm where it was; an out-of-reach target has no answer
    arm.set_joints(before)
    assert arm.ik([2.0, 0.0, 0.2], axis) is None
    np.testing.assert_allclose(arm.q, before)


def test_ik_gives_way_to_another_branch_when_the_closest_is_refused(client):
    """``valid`` (the env passes a collision check) refuses the closest answer: another verified branch comes
    back, on the target and axis; refusing every answer gives None."""
    arm = Gen3Arm(client)
    seed = np.asarray(arm.config.ik_seed)
    target, axis = np.array([0.1, 0.05, 0.15]), np.array([0.0, 0.0, -1.0])
    closest = arm.ik(target, axis, seed=seed)
    assert closest is not None
    other = arm.ik(target, axis, seed=seed, valid=lambda q: float(np.abs(q - closest).max()) > 0.1)
    assert other is not None and float(np.abs(other - closest).max()) > 0.1
    arm.set_joints(other)
    pos, quat = arm.tip_pose()
    assert np.linalg.norm(pos - target) < arm.config.ik_position_tol
    assert Rotation.from_quat(quat).as_matrix()[:, 2] @ axis > math.cos(arm.config.ik_angle_tol)
    assert arm.ik(target, axis, seed=seed, valid=lambda q: False) is None


def test_bin_reachable_top_down(client):
    """The pedestal beside the long side reaches (nearly) the whole default bin top-down."""
    arm = Gen3Arm(client)
    ready = arm.ik([0.0, 0.0, 0.40], [0, 0, -1], seed=np.asarray(arm.config.ik_seed))
    xs, ys = np.linspace(-0.30, 0.30, 4), np.linspace(-0.20, 0.20, 3)
    floor = np.array([[x, y, 0.02] for x in xs for y in ys])
    assert reachability(arm, floor, seed=ready).all()
    mid = np.array([[x, y, 0.2] for x in xs for y in ys])
    assert reachability(arm, mid, seed=ready).mean() >= 0.9


# --- planned, time-parameterised motion -------------------------------------------------------------
DT = 1.0 / 240.0


def _world(client, dt=DT):
    p.setGravity(0, 0, -9.81, physicsClientId=client)
    p.setTimeStep(dt, physicsClientId=client)
    arm = Gen3Arm(client)
    q_a = arm.ik([-0.25, 0.0, 0.2], [0, 0, -1], seed=np.asarray(arm.config.ik_seed))
    q_b = arm.ik([0.25, 0.1, 0.3], [0, 0, -1], seed=q_a)
    return arm, q_a, q_b


def _wall(client):
    """A static wall across the path between the two hover poses of ``_world``."""
    shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.02, 0.3, 0.3], physicsClientId=client)
    return p.createMultiBody(0, shape, basePosition=[0.0, 0.0, 0.2], physicsClientId=client)


def _step(client):
    return lambda: p.stepSimulation(physicsClientId=client)


@pytest.mark.parametrize("dt", [1.0 / 240.0, 1.0 / 60.0])
def test_execute_drives_the_arm_to_its_target_without_resets(client, monkeypatch, dt):
    arm, q_a, q_b = _world(client, dt)
    traj = joint_trajectory(arm.q, [q_a, q_b], GEN3_LIMITS, dt)

    def teleport(*args, **kwargs):
        raise AssertionError("the arm was reset while dynamics ran")

    monkeypatch.setattr(p, "resetJointStatesMultiDof", teleport)
    monkeypatch.setattr(p, "resetJointState", teleport)
    seen = []
    res = arm.execute(traj, _step(client), on_step=lambda: seen.append(arm.command[0].copy()))
    assert res.completed and res.steps == len(traj) - 1 == len(seen)
    # the measured state, read back from pybullet, is at the goal; the tool tracked its path closely
    measured = np.array([s[0] for s in p.getJointStates(arm.body, arm._joint_list, physicsClientId=client)])
    np.testing.assert_allclose(arm.q, measured)
    assert np.abs(measured - q_b).max() < 1e-3
    assert res.tip_error < (0.5e-3 if dt < 0.01 else 3e-3)
    assert 0 < res.tracking_error < 0.01
    np.testing.assert_allclose(seen[-1], q_b)
    # holding is driven too: the motors keep the arm where it is against gravity
    assert arm.hold(round(0.5 / dt), _step(client), dt).completed
    assert np.abs(arm.q - q_b).max() < 1e-3


def test_an_arm_placed_kinematically_stays_put_when_the_world_steps(client):
    """After a driven move and a kinematic sweep elsewhere, stepping the world (e.g. a pile settling)
    holds the arm where it was placed rather than pulling it back to the last driven target."""
    arm, q_a, q_b = _world(client)
    assert arm.execute(joint_trajectory(arm.q, [q_a], GEN3_LIMITS, DT), _step(client)).completed
    assert arm.sweep_trajectory(joint_trajectory(arm.q, [q_b], GEN3_LIMITS, DT)).completed
    for _ in range(120):
        p.stepSimulation(physicsClientId=client)
    measured = np.array([s[0] for s in p.getJointStates(arm.body, arm._joint_list, physicsClientId=client)])
    assert np.abs(measured - q_b).max() < 1e-3


def test_execute_refuses_a_wrong_step_or_start(client):
    arm, q_a, q_b = _world(client)
    with pytest.raises(ValueError, match="physics step"):
        arm.execute(joint_trajectory(arm.q, [q_a], GEN3_LIMITS, 1.0 / 60.0), _step(client))
    with pytest.raises(ValueError, match="starts"):
        arm.execute(joint_trajectory(q_b, [q_a], GEN3_LIMITS, DT), _step(client))


def test_execute_stops_on_a_collision_and_names_the_link(client):
    arm, q_a, q_b = _world(client)
    arm.set_joints(q_a)
    wall = _wall(client)
    res = arm.execute(joint_trajectory(q_a, [q_b], GEN3_LIMITS, DT), _step(client))
    assert not res.completed and res.collision.body == wall and res.link in arm.link_names.values()


def test_sweep_trajectory_checks_every_sample(client):
    arm, q_a, q_b = _world(client)
    arm.set_joints(q_a)
    traj = joint_trajectory(q_a, [q_b], GEN3_LIMITS, 1.0 / 30.0)
    assert arm.sweep_trajectory(traj).completed
    np.testing.assert_allclose(arm.q, q_b)
    wall = _wall(client)
    arm.set_joints(q_a)
    hit = arm.sweep_trajectory(traj)
    assert not hit.completed and hit.collision.body == wall and hit.link == hit.collision.link


@pytest.mark.parametrize("a_shape, b_shape", [((3,), (3,)), ((4, 3), (4, 3)), ((3,), (5, 3)), ((3, 7, 3), (3, 7, 3)),
                                              ((3, 7, 3), (3, 1, 3))])
def test_cross_rows_is_numpys_cross_product_for_every_shape_the_hot_loops_use(a_shape, b_shape):
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=a_shape), rng.normal(size=b_shape)
    out = cross_rows(a, b)
    assert out.shape == np.broadcast_shapes(a_shape, b_shape)
    np.testing.assert_allclose(out, np.cross(a, b), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(cross_rows(np.eye(3)[0], np.eye(3)[1]), [0.0, 0.0, 1.0])  # x cross y = z


def test_cross_rows_of_one_pair_is_the_general_path_to_the_bit():
    """The scalar fast path for two float64 3-vectors must give the very bits of the (1, 3) row path: the IK and
    the hold check take it at every step, and a last-bit change would move every trajectory of a chaotic pile."""
    rng = np.random.default_rng(1)
    scale = 10.0 ** rng.uniform(-9, 3, size=(2000, 2, 1))
    pairs = rng.normal(size=(2000, 2, 3)) * scale
    pairs[::50, 0, 1] = -0.0
    for a, b in pairs:
        np.testing.assert_array_equal(cross_rows(a, b).view(np.int64), cross_rows(a[None], b[None])[0].view(np.int64))
    assert cross_rows(np.ones(3, dtype=np.float32), np.ones(3, dtype=np.float32)).shape == (3,)  # others: general


def test_tool_motion_matches_finite_differences_of_forward_kinematics(client):
    arm = Gen3Arm(client)
    rng = np.random.default_rng(3)
    q0 = rng.uniform(-1.0, 1.0, 7)
    qd, qdd = rng.uniform(-0.8, 0.8, 7), rng.uniform(-2.0, 2.0, 7)
    h = 1e-4

    def pose(t):
        return arm.kin.tool_pose(q0 + qd * t + 0.5 * qdd * t * t)

    position, R, v, omega, a, alpha = arm.tool_motion(q0, qd, qdd)
    (pm, Rm), (p0, R0), (pp, Rp) = pose(-h), pose(0.0), pose(h)
    np.testing.assert_allclose(position, p0)
    np.testing.assert_allclose(R, R0)
    np.testing.assert_allclose(R[:, 2], arm.kin.forward(q0)[1], atol=1e-12)  # column z = approach axis
    np.testing.assert_allclose(v, (pp - pm) / (2 * h), atol=1e-6)
    np.testing.assert_allclose(a, (pp - 2 * p0 + pm) / h**2, atol=1e-3)
    # angular velocity from the rotation's derivative, angular acceleration from omega's
    W = (Rp - Rm) / (2 * h) @ R0.T
    np.testing.assert_allclose(omega, [W[2, 1], W[0, 2], W[1, 0]], atol=1e-6)
    w_p = arm.kin.tool_motion(q0 + qd * h + 0.5 * qdd * h * h, qd + qdd * h, qdd)[3]
    w_m = arm.kin.tool_motion(q0 - qd * h + 0.5 * qdd * h * h, qd - qdd * h, qdd)[3]
    np.testing.assert_allclose(alpha, (w_p - w_m) / (2 * h), atol=1e-4)


def test_cartesian_trajectory_keeps_the_tool_on_its_line_and_axis(client):
    """Lift and carry with a vertical tool: the axis stays vertical and the tip on the line at every sample."""
    arm, q_a, _ = _world(client, 1.0 / 60.0)
    arm.set_joints(q_a)
    corners = np.array([arm.kin.forward(q_a)[0], [-0.25, 0.0, 0.5], [0.3, 0.1, 0.5]])
    traj, why = arm.cartesian_trajectory(q_a, corners[1:], [0, 0, -1], 1.0 / 60.0, x_axis=arm.kin.tip_x(q_a))
    assert why is None
    assert bound_violation(traj, GEN3_LIMITS) <= 1.0 + 1e-6
    tips = np.array([arm.kin.forward(q)[0] for q in traj.q])
    tilt = np.degrees(np.arccos(np.clip([arm.kin.forward(q)[1] @ [0, 0, -1] for q in traj.q], -1, 1)))
    assert tilt.max() < 0.5

    def off_line(a, b):
        u = np.clip((tips - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
        return np.linalg.norm(tips - (a + u[:, None] * (b - a)), axis=1)

    assert np.minimum(off_line(corners[0], corners[1]), off_line(corners[1], corners[2])).max() < 2e-3
    np.testing.assert_allclose(tips[-1], corners[-1], atol=1e-3)
    # and the driven arm follows it
    res = arm.execute(traj, _step(client))
    assert res.completed and res.tip_error < 3e-3


def test_a_driven_carry_loads_the_held_parcel_with_its_physical_wrench(client):
    """Known answer: along an executed lift-and-carry (tool axis fixed, so no rotation), the fixed
    constraint holding a 2 kg box transmits m (a_tool - g), with a_tool from tool_motion of the measured
    state; a teleported arm would show solver impulses here instead."""
    dt, mass = 1.0 / 60.0, 2.0
    arm, q_a, _ = _world(client, dt)
    arm.set_joints(q_a)
    tip, orn = arm.tip_pose()
    shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.1, 0.1, 0.15], physicsClientId=client)
    box = p.createMultiBody(mass, shape, basePosition=(tip + [0, 0, -0.15]).tolist(), physicsClientId=client)
    for link in range(-1, p.getNumJoints(arm.body, physicsClientId=client)):
        p.setCollisionFilterPair(arm.body, box, link, -1, 0, physicsClientId=client)
    inv = p.invertTransform(*p.getBasePositionAndOrientation(box, physicsClientId=client))
    child_p, child_o = p.multiplyTransforms(inv[0], inv[1], tip.tolist(), orn.tolist())
    cid = p.createConstraint(arm.body, arm.tip_link, box, -1, p.JOINT_FIXED, [0, 0, 0], [0, 0, 0], child_p,
                             childFrameOrientation=child_o, physicsClientId=client)
    p.changeConstraint(cid, maxForce=1e5, physicsClientId=client)
    traj, _ = arm.cartesian_trajectory(q_a, [[-0.25, 0.0, 0.45], [0.25, 0.1, 0.45]], [0, 0, -1], dt,
                                       x_axis=arm.kin.tip_x(q_a))
    measured, expected = [], []

    def record():
        measured.append(np.linalg.norm(p.getConstraintState(cid, physicsClientId=client)[:3]))
        _, _, _, _, a, _ = arm.tool_motion()
        expected.append(mass * np.linalg.norm(a - [0.0, 0.0, -9.81]))

    assert arm.execute(traj, _step(client), on_step=record).completed
    measured, expected = np.array(measured), np.array(expected)
    assert expected.max() - expected.min() > 1.0  # the carry's accelerations are visible in the load
    np.testing.assert_allclose(measured, expected, atol=0.2)
