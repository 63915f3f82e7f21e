"""Smooth surface segments of an observed cloud, and each point's lever arm to its segment's centre.

A held parcel's torque at the cup grows with the horizontal distance from the cup to the parcel's centre of mass,
so the wrench score is an instance-level quantity that per-point network features estimate poorly. The centroid of
the smooth surface a point lies on is a cheap, purely geometric stand-in for that centre: on a parcel's top face it
sits right above the centre of mass. Nothing here sees ground truth.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

LEVER_CHANNELS = 4  # offset to the segment centroid (x, y, z) and its horizontal length
SIZE_CHANNELS = 1  # the segment's radius of gyration
LEVER_UNIT = 0.1  # metres: lever arms and sizes enter the networks in decimetres, O(1) like the other features


def segment_surfaces(points: np.ndarray, normals: np.ndarray, radius: float = 0.02, min_cos: float = 0.8
                     ) -> np.ndarray:
    """(N,) segment labels: connected components of the graph joining points closer than ``radius`` whose normals
    agree (cosine above ``min_cos``). Creases and depth gaps between parcels cut the graph."""
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must both be (N, 3), got {points.shape} and {normals.shape}")
    if not -1.0 <= min_cos <= 1.0:
        raise ValueError(f"need -1 <= min_cos <= 1, got {min_cos}")
    return radius_components(points, radius, lambda a, b: np.einsum("ij,ij->i", normals[a], normals[b]) > min_cos)


def radius_components(points: np.ndarray, radius: float,
                      agree: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                      tree: cKDTree | None = None) -> np.ndarray:
    """(N,) int64 labels: connected components of the graph joining the points closer than ``radius`` where
    ``agree(a, b)`` (a boolean mask over the index pairs ``a``, ``b``; None: every such pair) holds. ``tree``: a
    ``cKDTree`` already built on these points (float64), to share its build."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    if not radius > 0:
        raise ValueError(f"need radius > 0, got {radius}")
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if tree is not None and tree.n != n:
        raise ValueError(f"the tree holds {tree.n} points, not these {n}")
    pairs = (cKDTree(points) if tree is None else tree).query_pairs(radius, output_type="ndarray")
    if agree is not None:
        pairs = pairs[agree(pairs[:, 0], pairs[:, 1])]
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def segment_means(values: np.ndarray, labels: np.ndarray, count: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(K, D) float64 mean of ``values`` (N, D) over each label 0..K-1 (NaN where a label has none), and (K,) how
    many rows each mean is of; K is ``count``, or one past the largest label."""
    values = np.asarray(values, dtype=np.float64)
    labels = np.asarray(labels, dtype=np.int64)
    if values.ndim != 2 or labels.shape != (len(values),):
        raise ValueError(f"need (N, D) values and one label per row, got {values.shape} and {labels.shape}")
    k = (int(labels.max()) + 1 if len(labels) else 0) if count is None else int(count)
    counts = np.bincount(labels, minlength=k)
    sums = np.stack([np.bincount(labels, values[:, d], minlength=k) for d in range(values.shape[1])], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / counts[:, None], counts


def offsets_to_centroids(points: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(N, 3) float64: from each point to the centroid of its segment (what the levers and sizes are made of;
    pass it to both when both are wanted)."""
    points = np.asarray(points, dtype=np.float64)
    labels = np.asarray(labels, dtype=np.int64)
    if labels.shape != (len(points),):
        raise ValueError(f"need one label per point, got {labels.shape} for {len(points)} points")
    if len(points) == 0:
        return np.zeros((0, 3))
    return segment_means(points, labels)[0][labels] - points


def segment_levers(points: np.ndarray, labels: np.ndarray, offsets: np.ndarray | None = None) -> np.ndarray:
    """(N, 4) float32: the offset from each point to its segment's centroid, then that offset's horizontal length
    (``offsets``: ``offsets_to_centroids(points, labels)`` when already computed)."""
    offsets = offsets_to_centroids(points, labels) if offsets is None else offsets
    return np.concatenate([offsets, np.linalg.norm(offsets[:, :2], axis=1, keepdims=True)], axis=1).astype(np.float32)


def segment_sizes(points: np.ndarray, labels: np.ndarray, offsets: np.ndarray | None = None) -> np.ndarray:
    """(N, 1) float32: the radius of gyration (RMS distance to the centroid) of each point's segment.

    How large the face a point lies on is: a small face is a parcel's side or a fragment, whose centroid is a poor
    stand-in for the centre of mass. In metres, independent of the point density. ``offsets`` as in
    ``segment_levers``.
    """
    squared = np.sum((offsets_to_centroids(points, labels) if offsets is None else offsets) ** 2, axis=1)
    labels = np.asarray(labels, dtype=np.int64)
    if len(labels) == 0:
        return np.zeros((0, SIZE_CHANNELS), dtype=np.float32)
    mean_squared = np.bincount(labels, squared) / np.bincount(labels)
    return np.sqrt(mean_squared[labels])[:, None].astype(np.float32)


def surface_levers(points: np.ndarray, normals: np.ndarray, radius: float = 0.02, min_cos: float = 0.8
                   ) -> np.ndarray:
    """:func:`segment_levers` of :func:`segment_surfaces`: the per-point lever arm feature."""
    return segment_levers(points, segment_surfaces(points, normals, radius, min_cos))
