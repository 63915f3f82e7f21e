"""Observation modes (``EnvConfig.obs_mode``): right spaces, both env checkers, one episode per seed in
every mode, and a ``state_dict`` that is the true scene (known boxes, library assets)."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium import spaces
from scipy.spatial.transform import Rotation

from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.envs.config import OBS_MODES, EnvConfig
from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox
from parcelpick_env.envs.observation import (NOT_IN_LIBRARY, asset_from_index, bin_from_vector, bin_vector,
                                             sample_cloud)
from parcelpick_env.envs.parcel_pick import ParcelPickEnv
from parcelpick_env.scene.config import MAX_PARCELS
from parcelpick_env.scene.scene import BinSpec

SMALL = dict(camera=CameraConfig(width=160, height=120), num_points=256)
TWO_BOXES = BoxScene([PlacedBox((0.30, 0.20, 0.10), 0.5, (-0.12, 0.05), 0.4),
                      PlacedBox((0.16, 0.12, 0.08), 1.25, (0.18, -0.10), -0.2, friction=0.9)])
ONE_BOX = BoxScene([PlacedBox((0.20, 0.15, 0.10), 0.4)])


def make(scene=TWO_BOXES, **kwargs) -> ParcelPickEnv:
    return ParcelPickEnv(**{**SMALL, "scene_factory": scene, **kwargs})


def test_pointcloud_is_the_default_and_keeps_todays_layout():
    env = make()
    try:
        assert env.config.obs_mode == "pointcloud"
        space = env.observation_space
        assert set(space.spaces) == {"points", "normals", "rgb", "depth"}
        assert space["points"] == spaces.Box(-10.0, 10.0, (256, 3), np.float32)
        assert space["depth"] == spaces.Box(0.0, float(env.config.camera.far), (120, 160, 1), np.float32)
        obs, info = env.reset(seed=0)
        assert space.contains(obs) and info["privileged"] is False
        assert "suction" not in info and "asset_seed" not in info
    finally:
        env.close()


def test_bad_obs_mode_is_one_clear_error():
    with pytest.raises(ValueError, match="obs_mode"):
        EnvConfig(obs_mode="state")


def test_same_seed_same_episode_in_every_mode():
    """Every mode captures and samples alike, so the images and the cloud agree bit for bit."""
    runs = {}
    for mode in OBS_MODES:
        env = ParcelPickEnv(num_parcels=2, layout="scattered", object_set="rectangular", obs_mode=mode, **SMALL)
        try:
            obs, _ = env.reset(seed=5)
            assert env.observation_space.contains(obs)
            runs[mode] = obs
        finally:
            env.close()
    cloud, rgbd, state = runs["pointcloud"], runs["rgbd"], runs["state_dict"]
    assert set(rgbd) == {"rgb", "depth"}
    np.testing.assert_array_equal(rgbd["rgb"], cloud["rgb"])
    np.testing.assert_array_equal(rgbd["depth"], cloud["depth"])
    np.testing.assert_array_equal(state["points"], cloud["points"])
    np.testing.assert_array_equal(state["normals"], cloud["normals"])
    assert "rgb" not in state


def test_state_dict_is_the_true_scene_of_known_boxes():
    env = make(obs_mode="state_dict")
    try:
        obs, info = env.reset(seed=0)
        assert info["privileged"] is True and info["suction"] is env.config.suction
        assert info["asset_seed"] == env.config.asset_seed
        assert int(obs["parcel_count"]) == 2
        np.testing.assert_array_equal(obs["parcel_mask"], np.r_[1, 1, np.zeros(MAX_PARCELS - 2)].astype(np.int8))
        np.testing.assert_allclose(obs["parcel_mass"][:2], [0.5, 1.25], rtol=1e-6)
        np.testing.assert_allclose(obs["parcel_extents"][:2], [[0.30, 0.20, 0.10], [0.16, 0.12, 0.08]], rtol=1e-6)
        np.testing.assert_allclose(obs["parcel_friction"][:3], [0.6, 0.9, 0.0], rtol=1e-6)  # the third is padding
        # resting flat where they were placed, centres of mass at the boxes' centres
        np.testing.assert_allclose(obs["parcel_position"][:2, :2], [[-0.12, 0.05], [0.18, -0.10]], atol=5e-3)
        np.testing.assert_allclose(obs["parcel_position"][:2, 2], [0.05, 0.04], atol=3e-3)
        np.testing.assert_allclose(obs["parcel_com"][:2], obs["parcel_position"][:2], atol=1e-6)
        yaw = Rotation.from_quat(obs["parcel_quaternion"][:2]).as_euler("xyz")[:, 2]
        np.testing.assert_allclose(yaw, [0.4, -0.2], atol=0.02)
        # the boxes are not library assets; padding is zero, with an identity orientation
        assert np.all(obs["parcel_asset_index"] == NOT_IN_LIBRARY)
        assert not obs["parcel_position"][2:].any() and not obs["parcel_mass"][2:].any()
        np.testing.assert_array_equal(obs["parcel_quaternion"][2:], np.tile([0, 0, 0, 1], (MAX_PARCELS - 2, 1)))
        np.testing.assert_array_equal(obs["bin"], bin_vector(env.config.bin))
    finally:
        env.close()


def test_state_dict_asset_index_maps_back_to_the_library_mesh():
    env = ParcelPickEnv(num_parcels=3, layout="scattered", object_set="mixed", obs_mode="state_dict", **SMALL)
    try:
        obs, info = env.reset(seed=2)
        library = AssetLibrary.default(info["asset_seed"])
        count = int(obs["parcel_count"])
        assert count == len(env.scene.parcels) > 0
        for k, parcel in enumerate(env.scene.parcels):
            asset = asset_from_index(library, int(obs["parcel_asset_index"][k]))
            assert asset.asset_id == parcel.asset.asset_id
            assert asset.mesh is parcel.asset.mesh
            np.testing.assert_allclose(obs["parcel_com"][k], parcel.world_com(), atol=1e-5)
        with pytest.raises(ValueError, match="asset index"):
            asset_from_index(library, NOT_IN_LIBRARY)
    finally:
        env.close()


def test_bin_vector_round_trips_any_bin():
    spec = BinSpec(inner_size=(0.6, 0.45), wall_height=0.3, wall_thickness=0.015, center_xy=(0.1, -0.2), floor_z=0.05)
    back = bin_from_vector(bin_vector(spec))
    np.testing.assert_allclose(back.inner_size + (back.wall_height, back.wall_thickness) + back.center_xy
                               + (back.floor_z,), spec.inner_size + (0.3, 0.015, 0.1, -0.2, 0.05), rtol=1e-6)
    with pytest.raises(ValueError, match="bin"):
        bin_from_vector(np.zeros(6))


@pytest.mark.parametrize("mode", OBS_MODES)
def test_env_checkers_pass_for_each_mode(mode):
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    tiny = dict(camera=CameraConfig(width=96, height=72), num_points=128)  # the checkers render often
    env = ParcelPickEnv(scene_factory=ONE_BOX, action_mode="pixel", obs_mode=mode, render_mode="rgb_array", **tiny)
    try:
        gym_check(env, skip_render_check=False)
        sb3_check(env, warn=False)
    finally:
        env.close()


def test_observed_normals_are_the_full_cloud_estimate_at_the_sampled_points():
    """The env captures without normals and estimates them at the sampled points only: the observation must
    equal what sampling a capture with every normal estimated (Open3D's, the camera default) gives."""
    env = make(camera=CameraConfig(width=160, height=120, depth_noise_std=0.002))
    try:
        obs, _ = env.reset(seed=3)
        assert env.frame is not None and env.frame.normals.shape == (0, 3)  # nothing estimated beyond the samples
        np.testing.assert_allclose(np.linalg.norm(obs["normals"], axis=1), 1.0, atol=1e-4)
        full = env.camera.capture(env.sim, env.scene, np.random.default_rng(0))
        bare = env.camera.capture(env.sim, env.scene, np.random.default_rng(0), normals=False)
        assert np.array_equal(bare.points, full.points) and len(full.normals) == len(full.points)
        points, normals = sample_cloud(full, env.scene.bin, 256, np.random.default_rng(5))
        points_bare, normals_bare = sample_cloud(bare, env.scene.bin, 256, np.random.default_rng(5),
                                                 env.camera.normals_at)
        np.testing.assert_array_equal(points_bare, points)
        np.testing.assert_allclose(normals_bare, normals, atol=1e-5)
        assert np.degrees(np.arccos(np.clip(normals[:, 2], -1, 1))).max() > 5  # noisy: not all +z
        with pytest.raises(ValueError, match="without normals"):
            sample_cloud(bare, env.scene.bin, 256, np.random.default_rng(5))
    finally:
        env.close()
