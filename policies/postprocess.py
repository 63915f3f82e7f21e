"""Shared post-processing for every policy: score-sorted NMS over candidate positions, then top-k."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from policies.base import Candidates

NMS_RADIUS = 0.02  # metres, as in SuctionNet and the paper


def nms_indices(points: np.ndarray, scores: np.ndarray, radius: float = NMS_RADIUS,
                max_keep: int | None = None) -> np.ndarray:
    """Greedy NMS in descending score order: returns kept indices, best first.

    Loops once per *kept* candidate (argmax over the alive mask + one ball query), never once per point.
    """
    points = np.asarray(points, dtype=np.float64)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) != len(scores):
        raise ValueError(f"need points (N, 3) and scores (N,), got {points.shape} and {scores.shape}")
    if radius < 0:
        raise ValueError(f"NMS radius must be >= 0, got {radius}")
    if max_keep is not None and max_keep < 0:
        raise ValueError(f"max_keep must be >= 0, got {max_keep}")
    finite = np.isfinite(scores) & np.isfinite(points).all(1)
    order = np.flatnonzero(finite)[np.argsort(-scores[finite], kind="stable")]
    if len(order) == 0 or max_keep == 0:
        return np.zeros(0, dtype=np.int64)
    sorted_pts = points[order]
    tree = cKDTree(sorted_pts)
    alive = np.ones(len(order), dtype=bool)
    kept: list[int] = []
    limit = len(order) if max_keep is None else max_keep
    pos = 0
    while len(kept) < limit:
        nxt = pos + int(np.argmax(alive[pos:]))
        if not alive[nxt]:
            break
        kept.append(nxt)
        if radius > 0:
            alive[tree.query_ball_point(sorted_pts[nxt], radius)] = False
        alive[nxt] = False
        pos = nxt + 1
        if pos >= len(order):
            break
    return order[np.asarray(kept, dtype=np.int64)]


def select_candidates(points: np.ndarray, normals: np.ndarray, scores: np.ndarray, top_k: int = 50,
                      nms_radius: float = NMS_RADIUS) -> Candidates:
    """NMS + top-k -> Candidates (float32, unit normals, descending score)."""
    if top_k < 0:
        raise ValueError(f"top_k must be >= 0, got {top_k}")
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != np.shape(points):
        raise ValueError(f"normals {normals.shape} must match points {np.shape(points)}")
    keep = nms_indices(points, scores, nms_radius, top_k)
    n = normals[keep]
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return Candidates(points=np.asarray(points, dtype=np.float32)[keep].reshape(-1, 3),
                      normals=n.astype(np.float32).reshape(-1, 3),
                      scores=np.asarray(scores, dtype=np.float32).reshape(-1)[keep])
