"""Random baseline: uniformly sampled points of the observed cloud, approached along their normals.

It is the floor every learned policy must beat, and a cheap smoke test of the evaluators.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from policies.base import Candidates, Policy
from policies.observation import point_cloud


class RandomPolicy(Policy):
    name = "random"

    def __init__(self, seed: int | None = 0) -> None:
        self._rng = np.random.default_rng(seed)

    def reset(self, seed: int | None = None) -> None:
        """Reseed for a reproducible episode; ``None`` keeps the current stream."""
        if seed is not None:
            self._rng = np.random.default_rng(seed)

    def predict(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None,
                top_k: int = 50) -> Candidates:
        if top_k < 1:
            raise ValueError(f"top_k must be >= 1, got {top_k}")
        points, normals = point_cloud(obs, "RandomPolicy", drop_invalid=True)
        norm = np.linalg.norm(normals, axis=1)
        valid = np.flatnonzero(norm > 1e-6)
        if valid.size == 0:
            raise ValueError("the observed cloud has no finite point with a non-zero normal")
        pick = self._rng.choice(valid, size=min(top_k, valid.size), replace=False)
        scores = np.sort(self._rng.random(pick.size))[::-1]
        return Candidates(points=points[pick].astype(np.float32),
                          normals=(normals[pick] / norm[pick, None]).astype(np.float32),
                          scores=scores.astype(np.float32))
