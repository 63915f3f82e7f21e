"""Pinhole projection between the world frame and pixels, and the approach-axis angles the crops use.

Pixel convention: column ``u`` and row ``v`` with pixel centres at integers, so pixel (row i, col j)
is ``(u, v) = (j, i)`` and ``u = fx * x / z + cx``. Extrinsics are camera -> world, OpenCV axes.
"""

from __future__ import annotations

import numpy as np



def world_to_camera(points: np.ndarray, extrinsics: np.ndarray) -> np.ndarray:
    """(N, 3) world points -> (N, 3) camera-frame points."""
    T = np.asarray(extrinsics, dtype=np.float64)
    return (np.asarray(points, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]


def project(points: np.ndarray, intrinsics: np.ndarray, extrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points -> pixel coordinates (N, 2) as (u, v) and camera z-depth (N,).

    Points behind the camera get NaN pixel coordinates.
    """
    K = np.asarray(intrinsics, dtype=np.float64)
    cam = world_to_camera(points, extrinsics)
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        safe_z = np.where(z > 1e-9, z, np.nan)
        u = K[0, 0] * cam[:, 0] / safe_z + K[0, 2]
        v = K[1, 1] * cam[:, 1] / safe_z + K[1, 2]
    return np.stack([u, v], axis=1), z


def approach_angles(normals: np.ndarray, extrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For outward normals ``n`` (approach ``-n``): the in-image angle of the approach axis' projection
    (radians, atan2 over camera (y, x)) and its tilt from world vertical (radians, 0 = straight down)."""
    n = np.asarray(normals, dtype=np.float64)
    approach_cam = -n @ np.asarray(extrinsics, dtype=np.float64)[:3, :3]
    image_angle = np.arctan2(approach_cam[:, 1], approach_cam[:, 0])
    norm = np.linalg.norm(n, axis=1)
    tilt = np.arccos(np.clip(n[:, 2] / np.maximum(norm, 1e-12), -1.0, 1.0))
    return image_angle, tilt


def eligible_points(depth: np.ndarray, points: np.ndarray, normals: np.ndarray, intrinsics: np.ndarray,
                    extrinsics: np.ndarray, min_vertical_cos: float, tolerance: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points a crop can describe and the policy may propose, shared by training and inference.

    A point qualifies when it projects inside the image onto a valid depth pixel that agrees with its
    camera depth within ``tolerance`` (the camera sees it, not something in front of it), and its
    outward normal's z component is at least ``min_vertical_cos``. Returns (indices, uv, z, unit normals)
    of the qualifying points.
    """
    h, w = depth.shape
    norm = np.linalg.norm(normals, axis=1)
    unit = normals / np.maximum(norm, 1e-12)[:, None]
    uv, z = project(points, intrinsics, extrinsics)
    col, row = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    inside = np.isfinite(uv).all(axis=1) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    seen = depth[np.where(inside, row, 0).astype(np.int64), np.where(inside, col, 0).astype(np.int64)]
    keep = np.flatnonzero(inside & (norm > 1e-6) & (seen > 0) & (np.abs(seen - z) < tolerance)
                          & (unit[:, 2] >= min_vertical_cos))
    return keep, uv[keep], z[keep], unit[keep]
