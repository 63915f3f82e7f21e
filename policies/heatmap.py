"""Image-space candidate extraction shared by the heatmap baselines (Normal-STD, Cao et al.).

SuctionNet's recipe: smooth the per-pixel score with a box filter, keep the best pixel of each grid
cell, rank the cells and keep the top ones; then lift those pixels to 3-D suction poses (a point from
depth, an outward normal) and hand them to the shared NMS / top-k.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter
from scipy.spatial import cKDTree

from policies.base import Candidates
from policies.observation import in_box
from policies.postprocess import NMS_RADIUS, select_candidates

NORMAL_RADIUS = 0.005  # metres between a pixel and the neighbours of its depth-gradient normal
MAX_NORMAL_STEP_PX = 8
CLOUD_NORMAL_DISTANCE = 0.005  # metres: a cloud point farther than this from a candidate lends it no normal


def box_filter(heatmap: np.ndarray, size: int, valid: np.ndarray | None = None) -> np.ndarray:
    """``size`` x ``size`` mean filter; pixels outside ``valid`` count as 0 and come out as -inf."""
    heat = np.asarray(heatmap, dtype=np.float64)
    if valid is not None:
        heat = np.where(valid, heat, 0.0)
    out = uniform_filter(heat, size=size, mode="nearest") if size > 1 else heat.copy()
    if valid is not None:
        out[~valid] = -np.inf
    return out


def grid_topk(heatmap: np.ndarray, cell: int = 10, top_k: int = 1024) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The argmax pixel of each ``cell`` x ``cell`` block, best blocks first, at most ``top_k``.

    Non-finite pixels (-inf / NaN) are never chosen; a block holding only those yields nothing.
    Returns (rows, cols, scores).
    """
    heat = np.asarray(heatmap, dtype=np.float64)
    if heat.ndim != 2:
        raise ValueError(f"heatmap must be 2-D, got shape {heat.shape}")
    if cell < 1 or top_k < 1:
        raise ValueError(f"cell and top_k must be >= 1, got cell={cell}, top_k={top_k}")
    h, w = heat.shape
    H, W = -(-h // cell) * cell, -(-w // cell) * cell
    padded = np.full((H, W), -np.inf)
    padded[:h, :w] = np.where(np.isfinite(heat), heat, -np.inf)
    blocks = padded.reshape(H // cell, cell, W // cell, cell).transpose(0, 2, 1, 3).reshape(H // cell, W // cell, -1)
    arg = blocks.argmax(axis=-1)
    best = np.take_along_axis(blocks, arg[..., None], axis=-1)[..., 0]
    block_r, block_c = np.nonzero(np.isfinite(best))
    order = np.argsort(-best[block_r, block_c], kind="stable")[:top_k]
    block_r, block_c = block_r[order], block_c[order]
    local = arg[block_r, block_c]
    rows, cols = block_r * cell + local // cell, block_c * cell + local % cell
    return rows, cols, heat[rows, cols]


def pixels_to_world(rows: np.ndarray, cols: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray,
                    extrinsics: np.ndarray) -> np.ndarray:
    """(K, 3) world points of pixels (OpenCV pinhole, camera-to-world ``extrinsics``)."""
    K, T = np.asarray(intrinsics, dtype=np.float64), np.asarray(extrinsics, dtype=np.float64)
    z = np.asarray(depth, dtype=np.float64)[rows, cols]
    cam = np.stack([(cols - K[0, 2]) * z / K[0, 0], (rows - K[1, 2]) * z / K[1, 1], z], axis=-1)
    return cam @ T[:3, :3].T + T[:3, 3]


def workspace_pixels(depth: np.ndarray, intrinsics: np.ndarray, extrinsics: np.ndarray,
                     workspace: np.ndarray | None) -> np.ndarray:
    """(H, W) bool: pixels with depth whose world point lies in the box ``workspace`` ((2, 3): min, max corner).

    An image-space policy also sees the bin's walls and rim and the floor around the bin; the env refuses picks
    outside the bin (``info['workspace']``), so those pixels must never become candidates. ``None``: every pixel
    with depth.
    """
    depth = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    if workspace is None:
        return valid
    lo, hi = np.asarray(workspace, dtype=np.float64).reshape(2, 3)
    rows, cols = np.nonzero(valid)
    points = pixels_to_world(rows, cols, depth, intrinsics, extrinsics)
    valid[rows, cols] = in_box(points, lo, hi)
    return valid


def depth_normals(rows: np.ndarray, cols: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray,
                  extrinsics: np.ndarray, radius: float = NORMAL_RADIUS) -> np.ndarray:
    """World-frame normals at pixels from central differences of the unprojected depth.

    The neighbours sit about ``radius`` metres away on the surface (so the estimate is as smooth at
    640x480 as at 160x120). A neighbour without depth falls back to the centre pixel (a one-sided
    difference); where no difference is usable the normal faces the camera. Orientation is left to
    ``orient_towards``.
    """
    d = np.asarray(depth)
    h, w = d.shape
    fx = float(np.asarray(intrinsics)[0, 0])
    step = np.clip(np.rint(radius * fx / np.maximum(d[rows, cols], 1e-6)), 1, MAX_NORMAL_STEP_PX).astype(np.int64)

    def neighbour(dr: np.ndarray, dc: np.ndarray) -> np.ndarray:
        r, c = np.clip(rows + dr, 0, h - 1), np.clip(cols + dc, 0, w - 1)
        hole = d[r, c] <= 0
        r, c = np.where(hole, rows, r), np.where(hole, cols, c)
        return pixels_to_world(r, c, d, intrinsics, extrinsics)

    zero = np.zeros_like(step)
    normals = np.cross(neighbour(zero, step) - neighbour(zero, -step), neighbour(step, zero) - neighbour(-step, zero))
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    towards_camera = np.asarray(extrinsics, dtype=np.float64)[:3, 3] - pixels_to_world(rows, cols, d, intrinsics,
                                                                                       extrinsics)
    fallback = towards_camera / np.maximum(np.linalg.norm(towards_camera, axis=1, keepdims=True), 1e-12)
    return np.where(norm > 1e-12, normals / np.maximum(norm, 1e-12), fallback)


def orient_towards(normals: np.ndarray, points: np.ndarray, viewpoint: np.ndarray) -> np.ndarray:
    """Flip normals that face away from ``viewpoint`` (the camera sees only outward faces)."""
    flip = np.einsum("ij,ij->i", normals, np.asarray(viewpoint)[None, :] - points) < 0
    return np.where(flip[:, None], -normals, normals)


def pixels_to_candidates(rows: np.ndarray, cols: np.ndarray, scores: np.ndarray, depth: np.ndarray,
                         intrinsics: np.ndarray, extrinsics: np.ndarray, *,
                         cloud_points: np.ndarray | None = None, cloud_normals: np.ndarray | None = None,
                         nms_radius: float = NMS_RADIUS, top_k: int = 50) -> Candidates:
    """Lift ranked pixels to suction poses and apply the shared NMS / top-k.

    Normals come from the nearest point of the observed cloud (the env's Open3D estimates) when it
    lies within ``CLOUD_NORMAL_DISTANCE``, else from the depth image: a sparse cloud's nearest point
    may sit on a neighbouring parcel. Normals are oriented towards the camera; pixels without depth
    are dropped.
    """
    depth = np.asarray(depth)
    if depth.ndim == 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    keep = depth[rows, cols] > 0
    rows, cols, scores = rows[keep], cols[keep], np.asarray(scores)[keep]
    points = pixels_to_world(rows, cols, depth, intrinsics, extrinsics)
    normals = depth_normals(rows, cols, depth, intrinsics, extrinsics)
    if cloud_points is not None and cloud_normals is not None and len(cloud_points) > 0 and len(rows) > 0:
        tree = cKDTree(np.asarray(cloud_points, dtype=np.float64), balanced_tree=False, compact_nodes=False)
        distance, nearest = tree.query(points, distance_upper_bound=CLOUD_NORMAL_DISTANCE)
        found = np.isfinite(distance)
        cloud = np.zeros_like(normals)
        cloud[found] = np.asarray(cloud_normals, dtype=np.float64)[nearest[found]]
        length = np.linalg.norm(cloud, axis=1, keepdims=True)
        usable = found[:, None] & (length > 1e-6)  # a missing or degenerate cloud normal keeps depth's
        normals = np.where(usable, cloud / np.maximum(length, 1e-12), normals)
    normals = orient_towards(normals, points, np.asarray(extrinsics, dtype=np.float64)[:3, 3])
    return select_candidates(points, normals, np.asarray(scores, dtype=np.float64), top_k=top_k, nms_radius=nms_radius)
