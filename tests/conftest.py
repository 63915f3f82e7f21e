"""Shared fixtures: one small settled pile and its camera frame, built once per test session.

``small_scene`` is read-only by convention: tests that move bodies must build their own pile
(``small_sim`` holds the bodies, so moving them would change what later tests see).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest

from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.camera.camera import Camera
from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.camera.frame import CameraFrame
from parcelpick_env.scene.config import PileConfig
from parcelpick_env.scene.pile import build_pile
from parcelpick_env.scene.scene import Scene
from parcelpick_env.sim.simulator import Simulator

SMALL_SCENE_SEED = 7
SMALL_CAMERA = CameraConfig(width=160, height=120, depth_noise_std=0.0)  # noise-free: exact geometry


@pytest.fixture
def one_torch_thread():
    """One intra-op torch thread: OpenMP spin-waiting on an oversubscribed 2-core box is ~20x slower."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


class SmallScene(NamedTuple):
    scene: Scene
    frame: CameraFrame


@pytest.fixture(scope="session")
def library() -> AssetLibrary:
    return AssetLibrary.default(0)


@pytest.fixture(scope="session")
def small_sim():
    with Simulator() as sim:
        yield sim


@pytest.fixture(scope="session")
def small_camera() -> Camera:
    return Camera(SMALL_CAMERA)


@pytest.fixture(scope="session")
def small_scene(small_sim: Simulator, small_camera: Camera, library: AssetLibrary) -> SmallScene:
    """A settled 4-parcel stacked mixed train pile and its noise-free 160x120 capture."""
    config = PileConfig(num_parcels=4, layout="stacked", object_set="mixed", split="train")
    scene = build_pile(small_sim, config, seed=SMALL_SCENE_SEED, library=library)
    frame = small_camera.capture(small_sim, scene, np.random.default_rng(0))
    return SmallScene(scene=scene, frame=frame)
