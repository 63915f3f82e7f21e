"""Tiny synthetic parcel scenes with geometric labels, for tests and for smoke-testing the trainer.

Boxes on a floor, sampled on their top faces, their sides and the floor. Labels mimic the real ones in shape only:
seal falls off near face edges, wrench falls with the lever arm to the box centre, the floor is not graspable.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
from torch.utils.data import Dataset

CUP_RADIUS = 0.010


def synthetic_scene(rng: np.random.Generator, num_points: int = 1024, max_boxes: int = 4) -> dict[str, np.ndarray]:
    k = int(rng.integers(1, max_boxes + 1))
    cells = rng.permutation(4)[:k]  # 2x2 grid of 0.2 m cells: no overlaps
    centres = np.stack([0.1 + 0.2 * (cells % 2), 0.1 + 0.2 * (cells // 2)], 1) + rng.uniform(-0.02, 0.02, (k, 2))
    half = rng.uniform([0.03, 0.03, 0.02], [0.08, 0.08, 0.08], (k, 3))
    n_floor = num_points // 4
    n_box = num_points - n_floor
    # per box: top and four sides, sampled in proportion to area
    owner = rng.integers(0, k, n_box)
    face = rng.choice(5, n_box, p=[0.6, 0.1, 0.1, 0.1, 0.1])
    u, v = rng.uniform(-1, 1, n_box), rng.uniform(-1, 1, n_box)
    h = half[owner]
    local = np.zeros((n_box, 3))
    normal = np.zeros((n_box, 3))
    top = face == 0
    local[top] = np.c_[u[top] * h[top, 0], v[top] * h[top, 1], h[top, 2]]
    normal[top] = (0, 0, 1)
    for f, axis, sign in ((1, 0, 1), (2, 0, -1), (3, 1, 1), (4, 1, -1)):
        m = face == f
        other = 1 - axis
        local[m, axis] = sign * h[m, axis]
        local[m, other] = u[m] * h[m, other]
        local[m, 2] = v[m] * h[m, 2]
        normal[m, axis] = sign
    box_pts = local + np.c_[centres[owner], half[owner, 2]]
    # distance to the nearest face edge (in-face coordinates)
    edge = np.where(top, np.minimum(h[:, 0] - np.abs(local[:, 0]), h[:, 1] - np.abs(local[:, 1])),
                    np.minimum(h[:, 2] - np.abs(local[:, 2]), np.abs(np.abs(local[:, 0]) - h[:, 0]) +
                               np.abs(np.abs(local[:, 1]) - h[:, 1])))
    seal = np.clip((edge - CUP_RADIUS) / CUP_RADIUS, 0, 1)
    lever = np.linalg.norm(local[:, :2] * top[:, None], axis=1)
    wrench = np.where(top, np.clip(1 - lever / 0.06, 0, 1), 0.2)
    floor = np.c_[rng.uniform(0, 0.4, n_floor), rng.uniform(0, 0.4, n_floor), np.zeros(n_floor)]
    points = np.concatenate([box_pts, floor])
    normals = np.concatenate([normal, np.tile([0.0, 0.0, 1.0], (n_floor, 1))])
    labels = np.concatenate([np.c_[seal, wrench, np.ones(n_box), np.ones(n_box)],
                             np.tile([1.0, 0.0, 1.0, 0.0], (n_floor, 1))])
    object_ids = np.concatenate([owner + 1, np.zeros(n_floor, int)])
    points += rng.normal(0, 0.001, points.shape)
    order = rng.permutation(num_points)
    return {"points": points[order].astype(np.float32), "normals": normals[order].astype(np.float32),
            "labels": labels[order].astype(np.float32), "object_ids": object_ids[order].astype(np.int64)}


class SyntheticSuctionDataset(Dataset):
    """Same sample schema as ``dataset.torch_dataset.ParcelSuctionDataset``."""

    def __init__(self, num_scenes: int = 16, num_points: int = 1024, seed: int = 0,
                 transform: Callable[[dict], dict] | None = None):
        if num_scenes <= 0 or num_points < 16:
            raise ValueError(f"need num_scenes > 0 and num_points >= 16, got {num_scenes}, {num_points}")
        self.num_scenes, self.num_points, self.seed, self.transform = num_scenes, num_points, seed, transform

    def __len__(self) -> int:
        return self.num_scenes

    def __getitem__(self, i: int) -> dict[str, Any]:
        if not 0 <= i < self.num_scenes:
            raise IndexError(i)
        sample = synthetic_scene(np.random.default_rng([self.seed, i]), self.num_points)
        return self.transform(sample) if self.transform is not None else sample
