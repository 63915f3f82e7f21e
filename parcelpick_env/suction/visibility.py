"""Visibility score: the fraction of each parcel the camera sees, by ray casting the camera's pixels.

Visible pixels of object ``k`` are the camera rays whose FIRST hit is ``k`` (parcels and occluders
such as bin walls in one scene, one ``cast_rays``). Its pixels "rendered alone" are the rays that
hit ``k`` at all: its visible pixels plus the occluded rays through the projection of its bounding
box that hit ``k`` when tested against ``k`` alone (one any-hit query per parcel). Both counts use
the same pixel rays, so the ratio is in [0, 1].
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import open3d as o3d
import trimesh

from parcelpick_env.suction.geometry import O3D_INVALID_ID, build_scene, o3d_tensor, validate_meshes


def camera_rays(intrinsics: np.ndarray, extrinsics: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H*W, 6) float32 world-frame rays of every pixel, row-major, OpenCV convention.

    Pixel ``(row v, col u)`` looks through image point ``(u, v)``; ``extrinsics`` is camera->world.
    Directions have unit z-depth in the camera frame, so ``t_hit`` is the pixel's depth.
    """
    K = np.asarray(intrinsics, dtype=np.float64)
    T = np.asarray(extrinsics, dtype=np.float64)
    x = ((np.arange(width) - K[0, 2]) / K[0, 0]).astype(np.float32)
    y = ((np.arange(height) - K[1, 2]) / K[1, 1]).astype(np.float32)
    rotation = T[:3, :3].astype(np.float32)
    rays = np.empty((height, width, 6), dtype=np.float32)
    rays[..., :3] = T[:3, 3]
    rays[..., 3:] = (x[None, :, None] * rotation[:, 0] + y[:, None, None] * rotation[:, 1]
                     + rotation[:, 2])
    return rays.reshape(-1, 6)


def object_visibility(meshes: Sequence[trimesh.Trimesh], intrinsics: np.ndarray,
                      extrinsics: np.ndarray, width: int, height: int,
                      occluders: Sequence[trimesh.Trimesh] = (), num_threads: int = 0) -> np.ndarray:
    """(M,) visible pixels in the full scene / pixels when rendered alone, per parcel.

    Parcels the camera cannot see even alone (0 alone-pixels) get 0. ``num_threads`` is Open3D's
    thread count (0: every core).
    """
    meshes = validate_meshes(meshes, "meshes")
    occluders = validate_meshes(occluders, "occluders")
    intrinsics = np.asarray(intrinsics, dtype=np.float64)
    extrinsics = np.asarray(extrinsics, dtype=np.float64)
    if intrinsics.shape != (3, 3) or not np.all(np.isfinite(intrinsics)):
        raise ValueError(f"intrinsics must be a finite (3, 3) matrix, got shape {intrinsics.shape}")
    if not (intrinsics[0, 0] > 0 and intrinsics[1, 1] > 0):
        raise ValueError("intrinsics must have positive focal lengths fx, fy")
    if extrinsics.shape != (4, 4) or not np.all(np.isfinite(extrinsics)):
        raise ValueError(f"extrinsics must be a finite (4, 4) matrix, got shape {extrinsics.shape}")
    rotation = extrinsics[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-5):
        raise ValueError("extrinsics must be a rigid camera->world transform (orthonormal rotation)")
    if isinstance(num_threads, bool) or not isinstance(num_threads, int) or num_threads < 0:
        raise ValueError(f"num_threads must be an int >= 0, got {num_threads!r}")
    if int(width) != width or int(height) != height or width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive integers, got {width}x{height}")
    num_objects = len(meshes)
    if num_objects == 0:
        return np.zeros(0, dtype=np.float64)

    rays = camera_rays(intrinsics, extrinsics, int(width), int(height))
    full = build_scene(list(meshes) + list(occluders))
    first = full.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=num_threads)["geometry_ids"]
    first = first.numpy().astype(np.int64)
    first[first == O3D_INVALID_ID] = -1
    visible = np.bincount(first[(first >= 0) & (first < num_objects)], minlength=num_objects)

    # Alone, object k covers its visible pixels plus those where something else hides it; a pixel
    # that sees nothing in the scene cannot see k alone either. Only the rest needs a ray test.
    alone = visible.copy()
    for k, mesh in enumerate(meshes):  # a loop over parcels, each one batched any-hit query
        pixels = _bbox_pixels(mesh, intrinsics, extrinsics, int(width), int(height))
        pixels = pixels[(first[pixels] >= 0) & (first[pixels] != k)]
        if len(pixels):
            hits = build_scene([mesh]).test_occlusions(o3d_tensor(rays[pixels]),
                                                       nthreads=num_threads)
            alone[k] += int(hits.numpy().sum())

    ratio = np.zeros(num_objects, dtype=np.float64)
    seen = alone > 0
    ratio[seen] = np.minimum(1.0, visible[seen] / alone[seen])
    return ratio


def _bbox_pixels(mesh: trimesh.Trimesh, intrinsics: np.ndarray, extrinsics: np.ndarray,
                 width: int, height: int) -> np.ndarray:
    """Flat indices of the pixels inside the projection of the mesh's bounding box.

    Rendered alone, an object covers only pixels inside the projection of its box; if the box
    reaches behind the camera the whole image is returned.
    """
    corners = trimesh.bounds.corners(mesh.bounds)
    world_to_camera = np.linalg.inv(extrinsics)
    local = corners @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    if np.any(local[:, 2] <= 1e-9):
        return np.arange(width * height)
    projected = local @ intrinsics.T
    uv = projected[:, :2] / projected[:, 2:3]
    u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int), 0)
    u1 = min(int(np.ceil(uv[:, 0].max())), width - 1)
    v1 = min(int(np.ceil(uv[:, 1].max())), height - 1)
    if u0 > u1 or v0 > v1:
        return np.zeros(0, dtype=np.int64)
    rows, cols = np.meshgrid(np.arange(v0, v1 + 1), np.arange(u0, u1 + 1), indexing="ij")
    return (rows * width + cols).ravel()
