"""What the camera sees around a candidate pick that bears on whether the cell holds it: the hold check's inputs.

Each pick is described by its policy score and by the observed cloud around it, nothing privileged:

- how far below the observed top it lies, and how much of the pile rises above it within 5, 10 and 15 cm
  horizontally (the highest rise, and the share of nearby points more than 1 cm above it): a parcel under or
  beside others is dragged by them when it rises, about the cup's axis, which the lip's torsion capacity rarely
  holds (README, 'Where the stacked cells' attempts go');
- the face's tilt (the normal's z) and its distance to the nearest tote wall;
- the lever to the centroid of the smooth surface it lies on and that surface's size
  (``policies.surface_segments``): a stand-in for the moment of the parcel's weight about the cup.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from policies.surface_segments import offsets_to_centroids, segment_sizes, segment_surfaces

RADII: tuple[float, ...] = (0.05, 0.10, 0.15)  # m: horizontal neighbourhoods for the rise features
ABOVE: float = 0.01  # m: a neighbour this much higher than the pick counts as above it
FEATURES: tuple[str, ...] = ("score", "below_top", *(f"rise_{int(r * 100)}cm" for r in RADII),
                             *(f"above_{int(r * 100)}cm" for r in RADII), "normal_z", "wall_distance", "lever",
                             "surface_size")


def hold_features(points: np.ndarray, normals: np.ndarray, picks: np.ndarray, pick_normals: np.ndarray,
                  scores: np.ndarray, workspace: np.ndarray | None) -> np.ndarray:
    """(K, len(FEATURES)) float32 for K picks, from the observed cloud (N, 3) with its normals (rows with NaN are
    camera dropouts and ignored) and ``workspace``, the tote's (2, 3) box from ``info`` (None: the cloud's own
    horizontal extent stands in)."""
    picks = np.asarray(picks, dtype=np.float64).reshape(-1, 3)
    out = np.zeros((len(picks), len(FEATURES)), dtype=np.float32)
    if len(picks) == 0:
        return out
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    finite = np.isfinite(points).all(axis=1) & np.isfinite(normals).all(axis=1)
    points, normals = points[finite], normals[finite]
    if len(points) == 0:
        raise ValueError("hold_features needs at least one finite observed point")
    z = points[:, 2]
    out[:, 0] = np.asarray(scores, dtype=np.float32).reshape(-1)
    out[:, 1] = z.max() - picks[:, 2]
    flat, pick_tree = cKDTree(points[:, :2]), cKDTree(picks[:, :2])
    for i, radius in enumerate(RADII):
        pairs = pick_tree.sparse_distance_matrix(flat, radius, output_type="ndarray")
        rise = np.zeros(len(picks))
        np.maximum.at(rise, pairs["i"], z[pairs["j"]] - picks[pairs["i"], 2])
        near = np.bincount(pairs["i"], minlength=len(picks))
        above = np.bincount(pairs["i"], weights=z[pairs["j"]] > picks[pairs["i"], 2] + ABOVE, minlength=len(picks))
        out[:, 2 + i] = rise
        out[:, 2 + len(RADII) + i] = above / np.maximum(near, 1)
    out[:, 2 + 2 * len(RADII)] = np.asarray(pick_normals, dtype=np.float64).reshape(-1, 3)[:, 2]
    if workspace is None:
        lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    else:
        box = np.asarray(workspace, dtype=np.float64).reshape(2, 3)
        lo, hi = box[0, :2], box[1, :2]
    out[:, 3 + 2 * len(RADII)] = np.minimum(picks[:, :2] - lo, hi - picks[:, :2]).min(axis=1)
    labels = segment_surfaces(points, normals)
    offsets = offsets_to_centroids(points, labels)
    sizes = segment_sizes(points, labels, offsets)[:, 0]
    nearest = cKDTree(points).query(picks)[1]
    out[:, 4 + 2 * len(RADII)] = np.linalg.norm(offsets[nearest, :2], axis=1)
    out[:, 5 + 2 * len(RADII)] = sizes[nearest]
    return out
