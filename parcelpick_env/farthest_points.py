"""Farthest-point sampling (FPS), the one implementation every caller uses: Open3D's C++ greedy FPS.

FPS picks a start point, then repeatedly the point farthest (Euclidean) from all those picked so far,
so a few samples cover a cloud evenly, small far clusters included. Open3D's
``PointCloud.farthest_point_down_sample`` does this exactly (squared distances, the lowest index wins a
tie) in O(N * k), single-threaded; it returns the sampled points in their input order, not indices, so
the index of each point rides through it in the colour channel (float64: exact for integers < 2**53).

Callers: the simulator's collision-hull vertex reduction (``sim/simulator.py``, start at the vertex
farthest from the mean), the dataset's fixed-size annotation sample (``dataset/annotate.py``, through
``fixed_size_sample``), and the diffusion policy's PointNet++ centres (``policies/diffusion/neighbourhood.py``).
Open3D's tensor-API FPS was measured 100x slower (about 50 s for 16,384 of 32,768 points), so it is not used.
Open3D is imported on first use, not with the module: the dataset reader and the policy's neighbourhoods import this
module, and a trainer whose centres are grid-sampled (the default) then runs where Open3D is not installed (a GPU
image, where its 0.9 GB cannot travel; docs/training.md).
"""

from __future__ import annotations

import numpy as np


def _cloud(points: np.ndarray, name: str = "points") -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"{name} must be a non-empty (N, 3) point cloud, got shape {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError(f"{name} must be finite")
    return points


def farthest_point_indices(points: np.ndarray, k: int, start: int = 0) -> np.ndarray:
    """Ascending indices of the ``k`` farthest-point samples of ``points`` (N, 3), the first being ``start``.

    Deterministic: the same cloud and start always give the same indices. ``k >= N`` returns all N indices.
    """
    points = _cloud(points)
    n = len(points)
    if int(k) != k or k < 1:
        raise ValueError(f"k must be an integer >= 1, got {k!r}")
    if int(start) != start or not 0 <= start < n:
        raise ValueError(f"start must be an index in [0, {n}), got {start!r}")
    if k >= n:
        return np.arange(n, dtype=np.int64)
    import open3d as o3d  # on first use: see the module docstring

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    tags = np.zeros((n, 3))
    tags[:, 0] = np.arange(n)
    cloud.colors = o3d.utility.Vector3dVector(tags)
    sampled = cloud.farthest_point_down_sample(int(k), int(start))
    return np.asarray(sampled.colors)[:, 0].astype(np.int64)


def fixed_size_sample(points: np.ndarray, k: int, rng: np.random.Generator, presample: float = 0.0) -> np.ndarray:
    """Exactly ``k`` indices into ``points`` (N, 3), evenly spread: FPS, deterministic under ``rng``.

    FPS costs O(N * k); ``presample > 0`` first keeps a uniform random ``presample * k`` subset (sorted), which
    bounds the cost while keeping FPS's even coverage; FPS starts at the subset's first point. A cloud of at
    most ``k`` points is returned whole and padded by repeating random points (sorted), so every record of a
    dataset has the same size.
    """
    points = _cloud(points)
    if int(k) != k or k < 1:
        raise ValueError(f"k must be an integer >= 1, got {k!r}")
    if not (np.isfinite(presample) and (presample == 0 or presample >= 1)):
        raise ValueError(f"presample must be 0 (off) or >= 1, got {presample!r}")
    n = len(points)
    if n <= k:
        extra = np.sort(rng.choice(n, size=k - n, replace=True)) if k > n else np.empty(0, np.int64)
        return np.concatenate([np.arange(n), extra]).astype(np.int64)
    candidates = np.arange(n)
    if presample > 0 and n > presample * k:
        candidates = np.sort(rng.choice(n, size=int(presample * k), replace=False))
    return candidates[farthest_point_indices(points[candidates], k)]
