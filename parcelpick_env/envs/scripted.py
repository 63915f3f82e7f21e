"""A scripted, observation-only picker for tests and benchmarks (not a learned policy).

1. Keep cloud points inside the bin whose 24 nearest neighbours lie on their tangent plane (within
   ``flat_tol``) with agreeing normals: places a 1 cm cup can seal on.
2. Of those, take the top layer (within ``band`` of the highest) and the connected patch
   (``link`` metres) holding the highest point.
3. Aim at the flat point nearest the patch centroid, along its estimated normal. Parcels on top come
   first, and a patch centroid is near the centre of mass of a flat-lying carton, so the cup's
   torque stays small.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from parcelpick_env.scene.scene import BinSpec


def flat_points(points: np.ndarray, normals: np.ndarray, k: int = 24, flat_tol: float = 0.003,
                min_cos: float = 0.95) -> np.ndarray:
    """Boolean mask of points whose k-neighbourhood is planar with consistent normals."""
    k = min(k, len(points))
    _, nbr = cKDTree(points).query(points, k=k)
    offsets = points[nbr] - points[:, None, :]
    residual = np.abs(np.einsum("mkd,md->mk", offsets, normals)).max(axis=1)
    agree = np.einsum("mkd,md->mk", normals[nbr], normals).min(axis=1)
    return (residual < flat_tol) & (agree > min_cos)


def top_patch_action(obs: dict[str, np.ndarray], bin_spec: BinSpec = BinSpec(), band: float = 0.02,
                     link: float = 0.02, wall_margin: float = 0.02) -> np.ndarray:
    """A ``pose`` action (point, normal); NaNs when nothing pickable is seen (an invalid action)."""
    pts = np.asarray(obs["points"], dtype=np.float64)
    nrm = np.asarray(obs["normals"], dtype=np.float64)
    half = np.asarray(bin_spec.inner_size) / 2 - wall_margin
    rel = pts[:, :2] - np.asarray(bin_spec.center_xy)
    inside = np.all(np.abs(rel) < half, axis=1) & (pts[:, 2] > bin_spec.floor_z + 0.005) & (nrm[:, 2] > 0.5)
    idx = np.flatnonzero(inside)
    if len(idx) < 3:
        return np.full(6, np.nan, dtype=np.float32)
    idx = idx[flat_points(pts[idx], nrm[idx])]
    if len(idx) == 0:
        return np.full(6, np.nan, dtype=np.float32)
    band_idx = idx[pts[idx, 2] > pts[idx, 2].max() - band]
    tree = cKDTree(pts[band_idx])
    _, labels = connected_components(tree.sparse_distance_matrix(tree, link, output_type="coo_matrix"),
                                     directed=False)
    patch = band_idx[labels == labels[int(np.argmax(pts[band_idx, 2]))]]
    centroid = pts[patch].mean(axis=0)
    j = patch[int(np.argmin(np.linalg.norm(pts[patch] - centroid, axis=1)))]
    normal = nrm[j] / np.linalg.norm(nrm[j])
    return np.concatenate([pts[j], normal]).astype(np.float32)
