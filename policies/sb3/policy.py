"""A saved PPO model (``python -m policies.sb3.train``) behind the Policy interface.

The model maps coarse depth features to one pixel in [-1, 1]^2; the pixel is lifted to a suction pose
with the shared heatmap helpers (depth back-projection, normal from the observed cloud or the depth),
exactly as ``ParcelPick-v0``'s ``pixel`` action mode does. The model file is data only (safetensors
weights and a JSON spec, ``policies.sb3.model_io``): loading one never runs code from it.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from parcelpick_env.envs.parcel_pick import pixel_from_action
from policies.base import Candidates, Policy
from policies.heatmap import pixels_to_candidates
from policies.observation import camera, depth_image, point_cloud
from policies.sb3.features import DEFAULT_GRID, depth_features
from policies.sb3.model_io import load_model

DEFAULT_MODEL = Path(__file__).with_name("ppo_pixel.safetensors")  # shipped; made by TRAIN_COMMAND
TRAIN_COMMAND = "python -m policies.sb3.train --timesteps 2000 --seed 0"


class SB3Policy(Policy):
    name = "sb3"

    def __init__(self, checkpoint: str | Path | None = None, far: float = 3.0,
                 grid: tuple[int, int] = DEFAULT_GRID, deterministic: bool = True) -> None:
        path = Path(checkpoint) if checkpoint is not None else DEFAULT_MODEL
        self.model, spec = load_model(path, TRAIN_COMMAND)
        expected = (grid[0] * grid[1],)
        if spec.observation_shape != expected or spec.action_shape != (2,):
            raise ValueError(f"{path} maps observations {spec.observation_shape} to actions {spec.action_shape}, "
                             f"but this policy builds {expected} depth features and needs (2,) pixel actions")
        self.far, self.grid, self.deterministic = far, grid, deterministic

    def predict(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None,
                top_k: int = 50) -> Candidates:
        depth = depth_image(obs, "the sb3 policy")
        K, T = camera(info, "the sb3 policy")
        points, normals = point_cloud(obs, "the sb3 policy", drop_invalid=True)
        action, _ = self.model.predict(depth_features(depth, self.grid, self.far), deterministic=self.deterministic)
        row, col = pixel_from_action(np.clip(action, -1.0, 1.0), depth.shape[1], depth.shape[0])
        return pixels_to_candidates(np.array([row]), np.array([col]), np.ones(1, np.float32), depth, K, T,
                                    cloud_points=points, cloud_normals=normals, top_k=top_k)
