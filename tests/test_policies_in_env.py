"""Every registered policy drives ParcelPick-v0: ranked, valid candidates and a usable action."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import parcelpick_env  # noqa: F401  (registers ParcelPick-v0)
from parcelpick_env.camera.config import CameraConfig
from policies.registry import PRIVILEGED_POLICIES, available_policies, make_policy


@pytest.fixture(scope="module")
def env_and_obs():
    env = gym.make("ParcelPick-v0", num_parcels=3, layout="scattered", object_set="rectangular",
                   camera=CameraConfig(width=160, height=120), num_points=1024)
    obs, info = env.reset(seed=4)
    yield env, obs, info
    env.close()


@pytest.fixture(scope="module")
def sb3_model(env_and_obs, tmp_path_factory):
    """A saved (untrained) PPO model with the training command's observation and action spaces."""
    from stable_baselines3 import PPO

    from policies.sb3.model_io import save_model
    from policies.sb3.train import DepthOnly

    env = gym.make("ParcelPick-v0", action_mode="pixel", num_parcels=1, camera=CameraConfig(width=160, height=120),
                   num_points=64)
    path = tmp_path_factory.mktemp("sb3") / "ppo.safetensors"
    save_model(PPO("MlpPolicy", DepthOnly(env), n_steps=16, batch_size=16, seed=0, device="cpu").policy, path)
    env.close()
    return path


@pytest.mark.parametrize("name", [n for n in available_policies() if n not in PRIVILEGED_POLICIES])
def test_policy_gives_ranked_valid_candidates_and_action(name, env_and_obs, sb3_model):
    env, obs, info = env_and_obs
    policy = make_policy(name, checkpoint=sb3_model) if name == "sb3" else make_policy(name)
    policy.reset(seed=0)
    candidates = policy.predict(obs, info, top_k=10)
    assert 1 <= len(candidates) <= 10
    assert np.all(np.diff(candidates.scores) <= 1e-6), "candidates must be sorted by descending score"
    np.testing.assert_allclose(np.linalg.norm(candidates.normals, axis=1), 1.0, atol=1e-4)
    lo, hi = info["workspace"]
    assert np.all(candidates.points >= lo - 0.02) and np.all(candidates.points <= hi + 0.02)
    action = policy.act(obs, info)
    assert env.action_space.contains(action), (name, action)


def test_bad_observation_is_a_clear_error(env_and_obs):
    _, obs, info = env_and_obs
    bad = dict(obs, points=np.full_like(obs["points"], np.nan), depth=np.full_like(obs["depth"], np.nan))
    for name in ("normal_std", "dexnet", "cao"):
        with pytest.raises(ValueError):
            make_policy(name).predict(bad, info)
    with pytest.raises(ValueError):
        make_policy("random").predict(dict(obs, points=np.zeros((0, 3)), normals=np.zeros((0, 3))), info)
