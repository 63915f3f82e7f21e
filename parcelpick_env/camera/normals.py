"""Surface normals of a camera point cloud, oriented towards the camera.

Two estimators, both local PCA (the normal is the covariance's smallest eigenvector):

- ``open3d``: Open3D's KNN estimate on the unorganised cloud (the reference; about a second per
  megapixel-ish cloud on a desktop core, several seconds at 640x480 on a loaded 2-core machine).
  ``knn_normals_at`` gives the same estimate at a few points only (the dataset labels 4,096 of 77k).
- ``organized``: the same PCA over each pixel's image window (``window x window`` pixels, about
  ``knn`` neighbours), skipping neighbours across a depth jump so normals do not bleed between a
  parcel and what lies under it. For a single overhead view, image neighbours are 3-D neighbours,
  and box filtering over a handful of offsets is an order of magnitude faster than a KD-tree.
"""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree


SCAN_PAIRS = 2 * 640 * 480  # knn_normals_at scans distances, not a tree, up to this many (query, point) pairs


def orient_towards(normals: np.ndarray, points: np.ndarray, viewpoint: np.ndarray) -> np.ndarray:
    """Flip normals that point away from ``viewpoint`` (in place and returned)."""
    flip = ((viewpoint - points) * normals).sum(axis=1) < 0
    normals[flip] *= -1
    return normals


def open3d_normals(points: np.ndarray, knn: int, viewpoint: np.ndarray) -> np.ndarray:
    """Open3D KNN normals of an (N, 3) cloud, facing ``viewpoint``."""
    if len(points) < 3:
        return np.tile([0.0, 0.0, 1.0], (len(points), 1))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=min(knn, len(points))))
    return orient_towards(np.asarray(pcd.normals), points, viewpoint)


def knn_normals_at(points: np.ndarray, at: np.ndarray, knn: int, viewpoint: np.ndarray) -> np.ndarray:
    """``open3d_normals(points, knn, viewpoint)[at]``, computed only at ``points[at]`` (M, 3).

    The same estimate as Open3D's (PCA of each point's ``knn`` nearest neighbours in the whole cloud, itself
    included, then faced to ``viewpoint``); it agrees with it to rounding (and nearest-neighbour ties), at
    the cost of M neighbourhoods instead of N: a dataset that keeps 4,096 of 50,000 points pays a tenth.
    """
    points = np.asarray(points, dtype=np.float64)
    at = np.asarray(at, dtype=np.int64).reshape(-1)
    if len(at) and (at.min() < 0 or at.max() >= len(points)):
        raise ValueError(f"at must index the {len(points)} points, got indices in [{at.min()}, {at.max()}]")
    if len(points) < 3 or len(at) == 0:
        return np.tile([0.0, 0.0, 1.0], (len(at), 1))
    k = min(knn, len(points))
    if len(at) * len(points) <= SCAN_PAIRS:
        # a few points (a pixel action's one): scanning every distance beats building the tree (8 ms of CPU
        # against 25 for one point of 307,200), the same k nearest, nearest first
        nbr = np.empty((len(at), k), dtype=np.int64)
        for row, q in enumerate(points[at]):
            diff = points - q
            d2 = np.einsum("ni,ni->n", diff, diff)
            part = np.argpartition(d2, k - 1)[:k]
            nbr[row] = part[np.argsort(d2[part], kind="stable")]
    else:
        # an unbalanced tree with loose boxes and 64-point leaves builds in 24 ms instead of 41 (307,200 points,
        # the whole 640x480 image) and answers the same exact k-NN queries, neighbours in the same order
        tree = cKDTree(points, leafsize=64, balanced_tree=False, compact_nodes=False)
        _, nbr = tree.query(points[at], k=k)
    patches = points[nbr.reshape(len(at), -1)]  # (M, k, 3)
    centred = patches - patches.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", centred, centred)
    normals = np.linalg.eigh(cov)[1][:, :, 0]  # eigh sorts eigenvalues ascending
    return orient_towards(np.ascontiguousarray(normals), points[at], viewpoint)


def smallest_eigenvectors(xx, xy, xz, yy, yz, zz) -> np.ndarray:
    """Unit eigenvectors of the smallest eigenvalue of many symmetric 3x3 matrices, in closed form.

    Batched ``eigh`` on hundreds of thousands of 3x3 matrices costs about a second; the
    trigonometric eigenvalue formula plus a cross product of two rows of ``A - lambda I`` is
    vectorised arithmetic only.
    """
    q = (xx + yy + zz) / 3
    p1 = xy**2 + xz**2 + yz**2
    p2 = (xx - q) ** 2 + (yy - q) ** 2 + (zz - q) ** 2 + 2 * p1
    p = np.sqrt(np.maximum(p2 / 6, 1e-30))
    bxx, byy, bzz = (xx - q) / p, (yy - q) / p, (zz - q) / p
    bxy, bxz, byz = xy / p, xz / p, yz / p
    det = bxx * (byy * bzz - byz**2) - bxy * (bxy * bzz - byz * bxz) + bxz * (bxy * byz - byy * bxz)
    phi = np.arccos(np.clip(det / 2, -1, 1)) / 3
    lam = q + 2 * p * np.cos(phi + 2 * np.pi / 3)
    # Rows of A - lambda I; the eigenvector is the largest cross product of two of them.
    a, b, c = xx - lam, yy - lam, zz - lam
    c01 = np.stack([xy * yz - xz * b, xz * xy - a * yz, a * b - xy * xy], -1)  # r0 x r1
    c02 = np.stack([xy * c - xz * yz, xz * xz - a * c, a * yz - xy * xz], -1)  # r0 x r2
    c12 = np.stack([b * c - yz * yz, yz * xz - xy * c, xy * yz - b * xz], -1)  # r1 x r2
    n01, n02, n12 = ((v * v).sum(-1) for v in (c01, c02, c12))
    vec = np.where((n01 >= n02)[:, None], c01, c02)
    best = np.maximum(n01, n02)
    vec = np.where((n12 > best)[:, None], c12, vec)
    length = np.sqrt(np.maximum(best, n12))
    return np.where(length[:, None] > 0, vec / np.maximum(length, 1e-30)[:, None], (0.0, 0.0, 1.0))


def organized_normals(points_image: np.ndarray, valid: np.ndarray, knn: int, viewpoint: np.ndarray,
                      depth_gate: float = 0.01) -> np.ndarray:
    """PCA normals over image windows of an organised (H, W, 3) cloud; returns (valid.sum(), 3).

    The window is the odd square nearest ``knn`` pixels. Neighbours whose distance to the camera
    differs from the centre pixel's by more than ``depth_gate`` metres are left out. Pixels with
    fewer than 3 usable neighbours get +z.
    """
    h, w, _ = points_image.shape
    half = max(1, int(round(math.sqrt(knn))) // 2)
    rows, cols = np.nonzero(valid)
    if len(rows) == 0:
        return np.zeros((0, 3))
    # Work on the valid pixels' bounding box only, padded by the window.
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    pts = points_image[r0:r1, c0:c1].astype(np.float64)
    ok_c = valid[r0:r1, c0:c1]
    hh, ww = ok_c.shape
    rel = pts - viewpoint
    dist = np.sqrt((rel * rel).sum(axis=2)).astype(np.float32)
    comps = [np.ascontiguousarray(pts[..., i], dtype=np.float32) for i in range(3)]
    PX, PY, PZ = (np.pad(c, half) for c in comps)
    V, D = np.pad(ok_c, half), np.pad(dist, half)
    cx, cy, cz = comps
    # Sums of neighbour offsets from the centre pixel (small numbers: float32 is exact enough).
    acc = {k: np.zeros((hh, ww), np.float32) for k in ("n", "x", "y", "z", "xx", "xy", "xz", "yy", "yz", "zz")}
    for dr in range(2 * half + 1):
        for dc in range(2 * half + 1):
            sl = (slice(dr, dr + hh), slice(dc, dc + ww))
            okf = (V[sl] & ok_c & (np.abs(D[sl] - dist) < depth_gate)).astype(np.float32)
            dx = (PX[sl] - cx) * okf
            dy = (PY[sl] - cy) * okf
            dz = (PZ[sl] - cz) * okf
            acc["n"] += okf
            acc["x"] += dx
            acc["y"] += dy
            acc["z"] += dz
            acc["xx"] += dx * dx
            acc["xy"] += dx * dy
            acc["xz"] += dx * dz
            acc["yy"] += dy * dy
            acc["yz"] += dy * dz
            acc["zz"] += dz * dz
    sel = (rows - r0, cols - c0)
    v = {k: a[sel].astype(np.float64) for k, a in acc.items()}
    n = np.maximum(v["n"], 1.0)
    mx, my, mz = v["x"] / n, v["y"] / n, v["z"] / n
    normals = smallest_eigenvectors(
        v["xx"] / n - mx * mx, v["xy"] / n - mx * my, v["xz"] / n - mx * mz,
        v["yy"] / n - my * my, v["yz"] / n - my * mz, v["zz"] / n - mz * mz,
    )
    normals[v["n"] < 3] = (0.0, 0.0, 1.0)
    return orient_towards(normals, points_image[rows, cols].astype(np.float64), viewpoint)
