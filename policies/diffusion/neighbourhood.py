"""PointNet++ sampling and grouping, precomputed in the data pipeline with scipy/Open3D (no Python loops over points).

The network then only gathers by index. Arrays produced per level ``l`` (level 0 = the input points):
``sa{l}_centres`` (M_l,) indices into level l-1, ``sa{l}_groups`` (M_l, S, nsample) neighbour indices into
level l-1 (S = number of radii), ``fp{l}_index`` / ``fp{l}_weight`` (N_{l-1}, 3) inverse-distance
interpolation from level l back to level l-1.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
from scipy.spatial import cKDTree

from parcelpick_env.farthest_points import farthest_point_indices
from policies.diffusion.config import DiffusionConfig
from policies.surface_segments import offsets_to_centroids, segment_levers, segment_sizes, segment_surfaces


def grid_sample(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` spatially uniform points: one point per occupied voxel, voxel size tuned to the count.

    A fast, deterministic stand-in for farthest-point sampling (which costs O(N*M) and ~0.1 s at 16k->4k).
    """
    n = len(points)
    if count >= n:
        return np.arange(n)
    order = np.random.default_rng(0).permutation(n)  # fixed: the same cloud always gives the same sample
    pts = points[order]
    lo = pts.min(0)
    extent = np.maximum(pts.max(0) - lo, 1e-6)
    voxel = float(np.sqrt(np.sort(extent)[1:].prod() / count))  # surfaces: occupied voxels ~ area / voxel^2
    first = np.zeros(0, dtype=np.int64)
    for _ in range(6):
        cells = np.floor((pts - lo) / voxel).astype(np.int64)
        dims = cells.max(0) + 1
        keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]  # 1-D keys: fast unique
        _, first = np.unique(keys, return_index=True)
        if len(first) >= count:
            break
        voxel *= 0.8 * np.sqrt(len(first) / count)
    if len(first) >= count:
        chosen = np.sort(first)[:count]  # first `count` voxels in permutation order: a random subset of voxels
    else:  # degenerate clouds (all points in a few voxels): fill with the remaining points
        rest = np.setdiff1d(np.arange(n), first)
        chosen = np.concatenate([np.sort(first), rest[: count - len(first)]])
    return order[chosen]


def sample_indices(points: np.ndarray, count: int, sampler: str) -> np.ndarray:
    """``count`` centre indices: farthest-point sampling from point 0 (``parcelpick_env.farthest_points``) or
    the voxel ``grid_sample``."""
    return farthest_point_indices(points, count) if sampler == "fps" else grid_sample(points, count)


def ball_group(tree: cKDTree, n: int, centres: np.ndarray, radii: tuple[float, ...], nsample: int,
               dilation: tuple[int, ...], workers: int = 1) -> np.ndarray:
    """(M, S, nsample) neighbour indices per radius; short balls are padded with the first (nearest) neighbour.

    One k-NN query serves all scales: scale s takes every d_s-th of the d_s*nsample nearest points inside r_s,
    so larger radii see a sparser, wider sample of their ball, as PointNet++'s index-order ball query does.
    """
    k = min(nsample * max(dilation), n)
    dist, idx = tree.query(centres, k=k, distance_upper_bound=max(radii), workers=workers)
    dist, idx = dist.reshape(len(centres), k), idx.reshape(len(centres), k)
    groups = np.empty((len(centres), len(radii), nsample), dtype=np.int64)
    for s, (r, d) in enumerate(zip(radii, dilation)):  # loop over the 3 scales only
        raw = np.arange(nsample) * d
        cols = np.minimum(raw, k - 1)
        sel, ok = idx[:, cols], dist[:, cols] <= r
        ok[:, raw >= k] = False
        sel = np.where(ok, sel, idx[:, :1])  # column 0 is the centre itself (distance 0)
        groups[:, s] = sel
    return groups


def interpolation(dst: np.ndarray, src: np.ndarray, workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """3-NN inverse-distance weights to carry features from ``src`` points back to ``dst`` points."""
    k = min(3, len(src))
    dist, idx = cKDTree(src).query(dst, k=k, workers=workers)
    dist, idx = dist.reshape(len(dst), k), idx.reshape(len(dst), k)
    if k < 3:
        dist = np.concatenate([dist, np.repeat(dist[:, :1], 3 - k, 1)], 1)
        idx = np.concatenate([idx, np.repeat(idx[:, :1], 3 - k, 1)], 1)
    w = 1.0 / (dist + 1e-8)
    return idx.astype(np.int64), (w / w.sum(1, keepdims=True)).astype(np.float32)


def level_sizes(config: DiffusionConfig, n: int) -> list[int]:
    """SA centre counts for an n-point cloud: the configured counts, scaled by n / num_points."""
    sizes, prev = [], n
    for m in config.sa_npoints:
        prev = max(1, min(prev, int(round(m * n / config.num_points))))
        sizes.append(prev)
    return sizes


def compute_neighbourhoods(points: np.ndarray, config: DiffusionConfig, workers: int = 1,
                           queries: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """All SA/FP index arrays for one cloud (see module docstring); ``workers``: scipy k-NN threads. ``queries``
    (M, 3): the finest interpolation (``fp1_index`` / ``fp1_weight``) at those points instead of the cloud's, which
    may be some of the cloud's own (``model_inputs(rows=)``: each row's is what the whole cloud's would hold there,
    to the bit, every query point being its own query) or others (``model_inputs_at``)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"points must be a non-empty (N, 3) array, got shape {points.shape}")
    finest = points if queries is None else np.asarray(queries, dtype=np.float64)
    out: dict[str, np.ndarray] = {}
    level = points
    for l, (m, radii) in enumerate(zip(level_sizes(config, len(points)), config.sa_radii), start=1):
        tree = cKDTree(level)
        centres = sample_indices(level, m, config.sampler).astype(np.int64)
        out[f"sa{l}_centres"] = centres
        out[f"sa{l}_groups"] = ball_group(tree, len(level), level[centres], radii, config.nsample,
                                          config.ball_dilation, workers)
        out[f"fp{l}_index"], out[f"fp{l}_weight"] = interpolation(finest if l == 1 else level, level[centres],
                                                                  workers)
        level = level[centres]
    return out


def segment_inputs(points: np.ndarray, normals: np.ndarray, config: DiffusionConfig,
                   queries: np.ndarray | None = None, workers: int = 1) -> dict[str, np.ndarray]:
    """The surface segments' lever arms (``surface_levers``) and sizes (``surface_size``) that the config uses, at
    every point; with ``queries``, at the queries too (rows after the points'), each in its nearest point's segment."""
    out: dict[str, np.ndarray] = {}
    points = np.asarray(points, dtype=np.float64)
    labels = segment_surfaces(points, normals, config.segment_radius, config.segment_min_cos)
    offsets = offsets_to_centroids(points, labels)  # once, for the levers and the sizes alike
    sizes = segment_sizes(points, labels, offsets) if config.segment_size else None
    cloud = points
    if queries is not None:
        nearest = cKDTree(points).query(queries, workers=workers)[1]
        cloud = np.concatenate([points, queries])
        offsets = np.concatenate([offsets, (points + offsets)[nearest] - queries])
        labels = np.concatenate([labels, labels[nearest]])
        sizes = None if sizes is None else np.concatenate([sizes, sizes[nearest]])
    if config.segment_levers or config.levers_in_encoder:
        out["surface_levers"] = segment_levers(cloud, labels, offsets)
    if sizes is not None:
        out["surface_size"] = sizes
    return out


def model_inputs(points: np.ndarray, normals: np.ndarray, config: DiffusionConfig, workers: int = 1,
                 rows: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Everything the model needs precomputed for one cloud: the neighbourhoods (PointNet++ encoder), and the
    surface segments' lever arms (``surface_levers``) and sizes (``surface_size``) where the config uses them.
    ``rows`` (indices of fewer than N points): the finest interpolation at those points only, the ones a decoded
    subset reads (``DiffusionSuction.encode(batch, rows)``); the segment channels stay at every point."""
    out: dict[str, np.ndarray] = {}
    if config.encoder == "pointnet2":
        queries = None
        if rows is not None and len(rows) < len(points):
            queries = np.asarray(points, dtype=np.float64)[np.asarray(rows, dtype=np.int64)]
        out.update(compute_neighbourhoods(points, config, workers, queries))
    if config.uses_segments:
        out.update(segment_inputs(points, normals, config))
    return out


def model_inputs_at(points: np.ndarray, normals: np.ndarray, queries: np.ndarray, query_normals: np.ndarray,
                    config: DiffusionConfig, workers: int = 1) -> dict[str, np.ndarray]:
    """The model's batch for the cloud ``points`` followed by ``queries`` (N + M rows of ``points`` and ``normals``),
    to encode ``points`` and read features at the queries alone: ``DiffusionSuction.encode(batch, rows)`` with
    ``rows = arange(N, N + M)`` (``candidates.py``: the depth image's points, denser than the encoded cloud).

    The encoder's levels sample and group ``points`` only, the density the model learnt at; the finest interpolation
    runs at the queries. A query joins the surface segment of its nearest point: segmenting the union instead joins
    parcels across gaps the encoded density keeps open (measured: Top-50 AP 46.0 against 57.8 at the encoded points on
    16 test scenes). PointNet++ encoders only: the PointNet ablation's global feature would pool the queries too.
    """
    if config.encoder != "pointnet2":
        raise ValueError(f"model_inputs_at needs the PointNet++ encoder, this config's is {config.encoder!r}")
    points = np.asarray(points, dtype=np.float64)
    queries = np.asarray(queries, dtype=np.float64)
    if queries.ndim != 2 or queries.shape[1] != 3 or len(queries) == 0:
        raise ValueError(f"queries must be a non-empty (M, 3) array, got shape {queries.shape}")
    out = compute_neighbourhoods(points, config, workers, queries=queries)
    out["points"] = np.concatenate([points, queries]).astype(np.float32)
    out["normals"] = np.concatenate([np.asarray(normals, dtype=np.float64),
                                     np.asarray(query_normals, dtype=np.float64)]).astype(np.float32)
    if config.uses_segments:
        out.update(segment_inputs(points, normals, config, queries, workers))
    return out


class NeighbourhoodTransform:
    """Dataset transform: adds :func:`model_inputs` to a sample dict (needs 'points' and 'normals'). Batches with the
    default collate when every cloud in the batch has the same number of points."""

    def __init__(self, config: DiffusionConfig, inner: Any = None):
        self.config = config
        self.inner = inner  # optional transform applied first (e.g. augmentation)

    def __call__(self, sample: Mapping[str, Any]) -> dict[str, Any]:
        sample = dict(self.inner(sample) if self.inner is not None else sample)
        sample.update(model_inputs(np.asarray(sample["points"]), np.asarray(sample["normals"]), self.config))
        return sample
