"""Jerk-limited trajectories (ruckig): bounds hold on the samples, endpoints are exact, paths are kept."""

from __future__ import annotations

import numpy as np
import pytest

from parcelpick_env.robot.timing import (
    GEN3_LIMITS,
    JERK_TOL,
    JointLimits,
    bound_violation,
    concatenate,
    hold_trajectory,
    joint_trajectory,
    path_trajectory,
)

DT = 1.0 / 240.0


def assert_within_limits(traj, limits=GEN3_LIMITS):
    v, a, j = limits.arrays()
    assert np.all(np.abs(traj.qd) <= v * (1 + 1e-6))
    assert np.all(np.abs(traj.qdd) <= a * (1 + 1e-6))
    jerk = np.abs(np.diff(traj.qdd, axis=0)) / traj.dt
    assert np.all(jerk <= j * (1 + JERK_TOL))
    # the reported derivatives are those of the sampled positions (not just claimed)
    np.testing.assert_allclose(np.diff(traj.q, axis=0) / traj.dt, 0.5 * (traj.qd[1:] + traj.qd[:-1]),
                               atol=a.max() * traj.dt)


def test_limits_validate_and_scale():
    with pytest.raises(ValueError, match="velocity"):
        JointLimits((1.0,) * 6, (1.0,) * 7, (1.0,) * 7)
    with pytest.raises(ValueError, match="jerk"):
        JointLimits((1.0,) * 7, (1.0,) * 7, (0.0,) * 7)
    half = GEN3_LIMITS.scaled(0.5)
    np.testing.assert_allclose(half.acceleration, np.array(GEN3_LIMITS.acceleration) / 4)
    # Kinova's hard joint limits (ros_kortex hard_joint_limits.yaml): large actuators J1-4, small J5-7
    assert GEN3_LIMITS.velocity == (1.33,) * 4 + (1.16,) * 3
    assert GEN3_LIMITS.acceleration == (4.94,) * 4 + (9.5,) * 3


def test_single_joint_duration_matches_closed_form():
    """Rest-to-rest over D with v, a, j all reached: T = D/v + v/a + a/j (7-phase jerk-limited profile)."""
    v, a, j = (x[0] for x in GEN3_LIMITS.arrays())
    goal = np.zeros(7)
    goal[0] = 2.0
    traj = joint_trajectory(np.zeros(7), [goal], GEN3_LIMITS, DT)
    expected = 2.0 / v + v / a + a / j
    assert traj.duration == pytest.approx(expected, rel=0.01, abs=DT)
    assert np.abs(traj.qd[:, 0]).max() == pytest.approx(v, rel=1e-6)  # the cruise reaches the limit
    assert np.abs(traj.qdd[:, 0]).max() == pytest.approx(a, rel=1e-3)
    np.testing.assert_array_equal(traj.q[:, 1:], 0.0)  # the other joints never move


def test_joint_trajectory_bounds_endpoints_and_straight_segments():
    start = np.array([0.0, -0.35, 0.0, -2.3, 0.0, -0.5, 1.57])
    mid = start + np.array([1.0, 0.5, -0.3, 0.8, -1.2, 0.4, 2.0])
    goal = mid - np.array([0.4, 0.2, 0.6, 0.1, 0.0, 0.9, 0.3])
    traj = joint_trajectory(start, [mid, goal], GEN3_LIMITS, DT)
    assert_within_limits(traj)
    np.testing.assert_array_equal(traj.q[0], start)
    np.testing.assert_array_equal(traj.q[-1], goal)
    np.testing.assert_array_equal(traj.qd[[0, -1]], 0.0)
    # every sample lies on one of the two straight segments (phase synchronisation)
    def off_segment(q, a, b):
        u = np.clip((q - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
        return np.linalg.norm(q - (a + u[:, None] * (b - a)), axis=1)
    dist = np.minimum(off_segment(traj.q, start, mid), off_segment(traj.q, mid, goal))
    assert dist.max() < 1e-9
    # the arm comes to rest at the inner waypoint
    at_mid = np.argmin(np.linalg.norm(traj.q - mid, axis=1))
    assert np.linalg.norm(traj.q[at_mid] - mid) < 1e-3 and np.abs(traj.qd[at_mid]).max() < 0.01


def test_path_trajectory_stays_on_the_path_within_bounds():
    s = np.linspace(0.0, 1.0, 41)[:, None]
    path = np.hstack([np.sin(2 * s), s, s**2, 0.5 * s, np.cos(s), 0 * s, -s])
    traj = path_trajectory(path, GEN3_LIMITS, DT)
    assert_within_limits(traj)
    assert bound_violation(traj, GEN3_LIMITS) <= 1.0 + 1e-6
    np.testing.assert_allclose(traj.q[0], path[0], atol=1e-12)
    np.testing.assert_allclose(traj.q[-1], path[-1], atol=1e-12)
    # on the underlying smooth curve: compare against it at the nearest parameter
    fine = np.linspace(0.0, 1.0, 20001)[:, None]
    curve = np.hstack([np.sin(2 * fine), fine, fine**2, 0.5 * fine, np.cos(fine), 0 * fine, -fine])
    nearest = np.min(np.linalg.norm(traj.q[:, None, :] - curve[None, ::10, :], axis=2), axis=1)
    assert nearest.max() < 2e-3
    # progress is monotone along the path (no backing up)
    progress = np.argmin(np.linalg.norm(traj.q[:, None, :] - path[None], axis=2), axis=1)
    assert np.all(np.diff(progress) >= 0)


def test_path_trajectory_stops_at_a_sharp_corner_instead_of_crawling():
    a, b, c = np.zeros(7), np.r_[0.8, np.zeros(6)], np.r_[0.8, 0.8, np.zeros(5)]
    path = np.vstack([np.linspace(a, b, 20), np.linspace(b, c, 20)[1:]])
    traj = path_trajectory(path, GEN3_LIMITS, DT)
    assert_within_limits(traj)
    at_corner = np.argmin(np.linalg.norm(traj.q - b, axis=1))
    assert np.linalg.norm(traj.q[at_corner] - b) < 1e-3 and np.abs(traj.qd[at_corner]).max() < 0.01
    legs = path_trajectory(path[:20], GEN3_LIMITS, DT).duration + path_trajectory(path[19:], GEN3_LIMITS, DT).duration
    assert traj.duration == pytest.approx(legs, abs=2 * DT)


def test_speed_scale_slows_the_same_path():
    path = np.linspace(np.zeros(7), np.full(7, 0.8), 20)
    fast = path_trajectory(path, GEN3_LIMITS, DT)
    slow = path_trajectory(path, GEN3_LIMITS, DT, speed_scale=0.5)
    assert slow.duration == pytest.approx(2 * fast.duration, rel=0.02)
    assert_within_limits(slow, GEN3_LIMITS.scaled(0.5))


def test_hold_and_concatenate():
    q = np.full(7, 0.3)
    hold = hold_trajectory(q, 0.1, DT)
    assert hold.duration >= 0.1 and np.all(hold.q == q) and np.all(hold.qd == 0)
    move = joint_trajectory(q, [q + 0.2], GEN3_LIMITS, DT)
    both = concatenate([hold, move])
    assert len(both) == len(hold) + len(move) - 1
    assert both.duration == pytest.approx(hold.duration + move.duration)
    assert np.all(np.diff(both.t) > 0)
    with pytest.raises(ValueError, match="does not start"):
        concatenate([move, hold])


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="start_q"):
        joint_trajectory(np.zeros(6), [np.zeros(7)])
    with pytest.raises(ValueError, match="path"):
        path_trajectory(np.zeros((5, 6)))
    with pytest.raises(ValueError, match="dt"):
        joint_trajectory(np.zeros(7), [np.ones(7)], dt=0.0)


def test_slowed_limits_keep_the_ramp_time_and_finish_sooner_than_a_retimed_move():
    """``slowed``: velocity s, acceleration and jerk s^2, so acceleration builds up as fast as at full speed;
    the same path then ends sooner than the full-speed move re-timed by s (``scaled``'s jerk s^3) by the
    ramps' difference, within the slowed bounds."""
    slow = GEN3_LIMITS.slowed(0.25)
    v, a, j = GEN3_LIMITS.arrays()
    np.testing.assert_allclose(slow.arrays()[0], v * 0.25)
    np.testing.assert_allclose(slow.arrays()[1], a / 16)
    np.testing.assert_allclose(np.array(slow.jerk) / np.array(slow.acceleration), j / a)  # the ramp's 0.1 s
    with pytest.raises(ValueError, match="speed_scale"):
        GEN3_LIMITS.slowed(1.5)
    path = np.linspace(np.zeros(7), np.full(7, 0.3), 20)
    slowed, retimed = path_trajectory(path, slow, DT), path_trajectory(path, GEN3_LIMITS, DT, 0.25)
    assert_within_limits(slowed, slow)
    # T = D/v + v/a + a/j: the ramp a/j is 0.1 s slowed and 0.1/s re-timed, the rest alike (a straight
    # joint line has no curvature terms), so the re-timed move is 0.1 (1/s - 1) = 0.3 s longer
    assert retimed.duration - slowed.duration == pytest.approx(0.3, abs=0.05)
