"""The one interface every policy implements: an observation in, ranked suction candidates out."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np


@dataclass
class Candidates:
    """Suction candidates sorted by descending score. ``normals`` are outward unit normals."""

    points: np.ndarray  # (K, 3) float32, world frame
    normals: np.ndarray  # (K, 3) float32
    scores: np.ndarray  # (K,) float32

    def __len__(self) -> int:
        return int(self.scores.shape[0])

    def best_action(self) -> np.ndarray:
        """The env's ``pose`` action (point, outward normal) for the top candidate."""
        if len(self) == 0:
            raise ValueError("no candidates to act on")
        return np.concatenate([self.points[0], self.normals[0]]).astype(np.float32)


class Policy(ABC):
    """Policies see only what the env observes (plus camera calibration from ``info``), never ground truth."""

    name: str = "policy"
    obs_mode: str = "pointcloud"  # the env observation mode it needs (parcelpick_env/envs/observation.py)
    action_mode: str = "pose"  # the env action mode its ``act`` answers in (the oracle's parting pushes: "pose_push")

    @abstractmethod
    def predict(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None,
                top_k: int = 50) -> Candidates:
        """Rank suction candidates for one observation."""

    def act(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> np.ndarray:
        return self.predict(obs, info, top_k=1).best_action()

    def reset(self, seed: int | None = None) -> None:
        """Called at the start of each episode; stateful or stochastic policies reseed here."""
