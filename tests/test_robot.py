"""The Gen3 URDF, its kinematics, verified IK and bounded-speed motion."""

from __future__ import annotations

import math

import numpy as np
import pybullet as p
import pytest
from scipy.spatial.transform import Rotation

from parcelpick_env.robot.arm import ArmConfig, Gen3Arm, reachability
from parcelpick_env.robot.gen3 import JOINTS, URDF_PATH, VELOCITY_LIMIT, SuctionToolSpec, gen3_suction_urdf


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


def test_numpy_kinematics_agree_with_pybullet(client):
    arm = Gen3Arm(client)
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = rng.uniform(arm.lower, arm.upper)
        arm.set_joints(q)
        pos, quat = arm.tip_pose()
        tip, axis, _, _ = arm.kin.forward(q)
        np.testing.assert_allclose(tip, pos, atol=1e-5)
        np.testing.assert_allclose(axis, Rotation.from_quat(quat).as_matrix()[:, 2], atol=1e-5)


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


def test_bin_reachable_top_down(client):
    """The pedestal beside the long side reaches (nearly) the whole default bin top-down."""
    arm = Gen3Arm(client)
    ready = arm.ik([0.0, 0.0, 0.40], [0, 0, -1], seed=np.asarray(arm.config.ik_seed))
    xs, ys = np.linspace(-0.30, 0.30, 4), np.linspace(-0.20, 0.20, 3)
    floor = np.array([[x, y, 0.02] for x in xs for y in ys])
    assert reachability(arm, floor, seed=ready).all()
    mid = np.array([[x, y, 0.2] for x in xs for y in ys])
    assert reachability(arm, mid, seed=ready).mean() >= 0.9


def test_trajectory_respects_joint_speed(client):
    arm = Gen3Arm(client)
    dt = 1.0 / 240.0
    goal = arm.q + np.array([1.0, -0.5, 0.3, 0.8, -1.2, 0.4, 2.0])
    traj = list(arm.trajectory([goal], dt))
    qs = np.array([q for q, _ in traj])
    qds = np.array([qd for _, qd in traj])
    assert np.abs(qds).max() <= VELOCITY_LIMIT * (1 + 1e-6)
    assert np.abs(np.diff(qs, axis=0)).max() <= VELOCITY_LIMIT * dt * (1 + 1e-6)
    np.testing.assert_allclose(qs[-1], goal, atol=1e-9)
    # the slowest joint sets the duration: 2 rad at a cosine profile's peak speed
    assert len(traj) * dt == pytest.approx(math.pi / 2 * 2.0 / VELOCITY_LIMIT, abs=2 * dt)


def test_sweep_detects_an_obstacle_in_the_path(client):
    arm = Gen3Arm(client)
    seed = np.asarray(arm.config.ik_seed)
    q_a = arm.ik([-0.25, 0.0, 0.2], [0, 0, -1], seed=seed)
    q_b = arm.ik([0.25, 0.0, 0.2], [0, 0, -1], seed=q_a)
    arm.set_joints(q_a)
    free = arm.sweep([q_b], 1 / 30)
    assert free.completed and free.collision is None
    wall = p.createMultiBody(0, p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.02, 0.3, 0.3], physicsClientId=client),
                             basePosition=[0.0, 0.0, 0.2], physicsClientId=client)
    arm.set_joints(q_a)
    hit = arm.sweep([q_b], 1 / 30)
    assert not hit.completed and hit.collision.body == wall
