"""The parting push (action_mode="pose_push", envs/push.py): known answers on one carton, the step's bookkeeping,
bad pushes refused, the env checkers, and a pick in this mode the same as in "pose" mode."""

from __future__ import annotations

import numpy as np
import pytest

from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.envs.config import EnvConfig, GraspConfig
from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox
from parcelpick_env.envs.parcel_pick import ParcelPickEnv

SMALL = dict(camera=CameraConfig(width=160, height=120), num_points=256)
SIDE, HEIGHT = 0.15, 0.10
CARTON = BoxScene([PlacedBox((SIDE, SIDE, HEIGHT), 0.5, (0.0, 0.0))])
GAP = 0.01  # m between the cup's side and the carton at the push's start
PICK, PUSH = 1.0, -1.0


def make(**kwargs) -> ParcelPickEnv:
    return ParcelPickEnv(**{**SMALL, "scene_factory": CARTON, "action_mode": "pose_push", **kwargs})


def beside(env: ParcelPickEnv, direction=(1.0, 0.0), height: float = 0.04) -> np.ndarray:
    """A push start with the cup's side GAP from the carton's face, ``height`` above the floor, facing ``direction``."""
    centre, _ = env.sim.body_pose(env.scene.parcels[0].body_id)
    d = np.array([*direction, 0.0])
    start = centre - d * (SIDE / 2 + env.config.suction.cup_radius + GAP)
    start[2] = env.scene.bin.floor_z + height
    return np.concatenate([start, d, [PUSH]]).astype(np.float32)


def carton_position(env: ParcelPickEnv) -> np.ndarray:
    return env.sim.body_pose(env.scene.parcels[0].body_id)[0]


@pytest.mark.parametrize("direction", [(1.0, 0.0), (0.0, -1.0)])
def test_a_push_moves_the_carton_its_distance_less_the_gap(direction):
    env = make()
    try:
        env.reset(seed=0)
        before = carton_position(env)
        _, reward, terminated, truncated, info = env.step(beside(env, direction))
        moved = carton_position(env) - before
        d = np.array([*direction, 0.0])
        along = float(moved @ d)
        expected = GraspConfig().push_distance - GAP  # the tool meets the face after the gap, then carries it
        assert info["outcome"] == "pushed" and info["failure"]["move"] is None
        assert abs(along - expected) < 0.02, moved
        assert float(np.linalg.norm(moved - along * d)) < 0.01, moved  # straight, and still on the floor
        # a push is no pick attempt: no reward, no attempt, no failure in the run
        assert (reward, terminated, truncated) == (0.0, False, False)
        assert (info["attempts"], info["pushes"], info["consecutive_failures"]) == (0, 1, 0)
        assert info["pushes_left"] == EnvConfig().max_pushes - 1
        assert info["R_grasp"] == 0.0 and info["parcels_remaining"] == 1
    finally:
        env.close()


def test_a_push_whose_descent_lands_on_a_parcel_is_refused_and_moves_nothing():
    env = make()
    try:
        env.reset(seed=0)
        before = carton_position(env)
        on_top = beside(env)
        on_top[:2] = before[:2]  # the start is inside the carton: the tool comes down on its top
        _, _, _, _, info = env.step(on_top)
        assert info["outcome"] == "unreachable"
        assert (info["failure"]["move"], info["failure"]["condition"]) == ("descend", "blocked")
        assert float(np.linalg.norm(carton_position(env) - before)) < 1e-3
        assert (info["attempts"], info["pushes"]) == (0, 1)
    finally:
        env.close()


def test_pushes_beyond_the_limit_and_vertical_pushes_are_invalid_actions():
    env = make(max_pushes=1)
    try:
        env.reset(seed=0)
        up = beside(env)
        up[3:6] = (0.0, 0.0, 1.0)
        _, _, _, _, info = env.step(up)
        assert info["outcome"] == "invalid_action" and "horizontal" in info["invalid_reason"]
        assert (info["attempts"], info["pushes"], info["consecutive_failures"]) == (1, 0, 1)
        env.step(beside(env, (-1.0, 0.0)))
        _, _, _, _, info = env.step(beside(env, (-1.0, 0.0)))
        assert info["outcome"] == "invalid_action" and "push limit" in info["invalid_reason"]
        assert (info["attempts"], info["pushes"], info["pushes_left"]) == (2, 1, 0)
    finally:
        env.close()
    with pytest.raises(ValueError, match="max_pushes"):
        EnvConfig(max_pushes=-1)
    with pytest.raises(ValueError, match="push_distance"):
        GraspConfig(push_distance=0.0)


def test_a_pick_in_pose_push_mode_is_the_pose_mode_pick():
    top = np.array([0.0, 0.0, HEIGHT, 0.0, 0.0, 1.0])
    runs = []
    for mode, action in (("pose", top), ("pose_push", np.append(top, PICK))):
        env = make(action_mode=mode)
        try:
            obs, _ = env.reset(seed=0)
            _, reward, _, _, info = env.step(action.astype(np.float32))
            runs.append((reward, info["outcome"], info["seal"], info["sim_time"], info["pushes"]))
        finally:
            env.close()
    assert runs[0] == runs[1] and runs[0][:2] == (1.0, "success")


def test_the_same_push_from_the_same_seed_ends_in_the_same_place():
    ends = []
    for _ in range(2):
        env = make()
        try:
            env.reset(seed=3)
            env.step(beside(env, (0.6, 0.8)))
            ends.append(carton_position(env))
        finally:
            env.close()
    np.testing.assert_array_equal(ends[0], ends[1])


def test_pose_push_mode_passes_the_env_checkers():
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    env = make(camera=CameraConfig(width=96, height=72), num_points=128)
    try:
        assert env.action_space.shape == (7,)
        gym_check(env)
        sb3_check(env, warn=False)
    finally:
        env.close()
