"""Geometry shared by the suction scores: tangent frames, disk ray patterns, Open3D ray scenes.

Every score is answered by Open3D's ``RaycastingScene`` (Embree, C++, multi-threaded): one batched
call per score, never a Python loop over candidates.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import open3d as o3d
import trimesh

O3D_INVALID_ID = int(o3d.t.geometry.RaycastingScene.INVALID_ID)


def o3d_tensor(array: np.ndarray) -> o3d.core.Tensor:
    """A copy of ``array`` as an Open3D tensor of the same dtype, on the CPU (Open3D's defaults)."""
    # Open3D's stubs list ``dtype`` and ``device`` as required, but the binding defaults both (to the array's
    # dtype and CPU:0), so the one-argument call that works at run time matches no stub overload.
    return o3d.core.Tensor(array)  # type: ignore[call-overload]


def tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents ``(u, w)`` per unit normal so that ``(u, w, n)`` is right-handed.

    The helper axis is the world axis least aligned with ``n``, so the frame is well conditioned
    for every direction.
    """
    n = np.asarray(normals, dtype=np.float64)
    helper = np.zeros_like(n)
    helper[np.arange(len(n)), np.argmin(np.abs(n), axis=1)] = 1.0
    u = np.cross(n, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = np.cross(n, u)
    return u, w


def ring_pattern(radii: Sequence[float], counts: Sequence[int], phase: float = 0.0) -> np.ndarray:
    """(K, 2) planar offsets: ``counts[i]`` points evenly spaced on a circle of ``radii[i]``.

    A radius of 0 contributes a single centre point whatever its count.
    """
    parts = []
    for radius, count in zip(radii, counts):
        if radius == 0:
            parts.append(np.zeros((1, 2)))
            continue
        theta = phase + 2.0 * np.pi * np.arange(count) / count
        parts.append(radius * np.stack([np.cos(theta), np.sin(theta)], axis=1))
    return np.concatenate(parts, axis=0) if parts else np.zeros((0, 2))


def frame_rays(points: np.ndarray, normals: np.ndarray, u: np.ndarray, w: np.ndarray,
               coefficients: np.ndarray) -> o3d.core.Tensor:
    """(N*K, 6) float32 rays laid out in each candidate's local frame ``(u, w, n)`` around ``p``.

    ``coefficients`` is (K, 6): ray ``k`` of candidate ``i`` starts at
    ``p_i + a u_i + b w_i + c n_i`` and points along ``d u_i + e w_i + f n_i`` for the row
    ``(a, b, c, d, e, f)``. One batched float32 matmul builds all rays (no (N, K, 3) temporaries).
    """
    count = len(points)
    basis = np.zeros((count, 7, 6), dtype=np.float32)
    basis[:, 0, :3] = u
    basis[:, 1, :3] = w
    basis[:, 2, :3] = normals
    basis[:, 3, :3] = points
    basis[:, 4, 3:] = u
    basis[:, 5, 3:] = w
    basis[:, 6, 3:] = normals
    coefficients = np.asarray(coefficients, dtype=np.float32)
    rows = np.concatenate([coefficients[:, :3], np.ones((len(coefficients), 1), np.float32),
                           coefficients[:, 3:]], axis=1)
    rays = np.empty((count, len(coefficients), 6), dtype=np.float32)
    np.matmul(rows[None], basis, out=rays)
    return o3d.core.Tensor.from_numpy(rays.reshape(-1, 6))  # shares memory, no copy


def surface_centroid(mesh: trimesh.Trimesh) -> np.ndarray:
    """(3,) area-weighted centroid of a mesh's surface: the limit of a dense surface sample's mean (the centre
    SuctionNet's wrench score uses), not the solid's centre of mass."""
    return (mesh.triangles_center * mesh.area_faces[:, None]).sum(axis=0) / mesh.area


def build_scene(meshes: Sequence[trimesh.Trimesh],
                offsets: np.ndarray | None = None) -> o3d.t.geometry.RaycastingScene:
    """One ray scene holding ``meshes`` (optionally translated by ``offsets[i]``).

    Geometry ids are assigned in order, so ``geometry_id == i`` is ``meshes[i]``.
    """
    scene = o3d.t.geometry.RaycastingScene()
    for i, mesh in enumerate(meshes):
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        if offsets is not None:
            vertices = vertices + offsets[i]
        geometry_id = scene.add_triangles(
            o3d_tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
            o3d_tensor(np.ascontiguousarray(mesh.faces, dtype=np.uint32)))
        if geometry_id != i:  # pragma: no cover - Open3D guarantees sequential ids
            raise RuntimeError(f"Open3D assigned geometry id {geometry_id} to mesh {i}")
    return scene


def validate_meshes(meshes: Sequence[trimesh.Trimesh], name: str) -> list[trimesh.Trimesh]:
    """Meshes as a list, each a non-empty, finite ``trimesh.Trimesh`` (else ValueError)."""
    meshes = list(meshes)
    for i, mesh in enumerate(meshes):
        if not isinstance(mesh, trimesh.Trimesh):
            raise ValueError(f"{name}[{i}] must be a trimesh.Trimesh, got {type(mesh).__name__}")
        if len(mesh.faces) == 0:
            raise ValueError(f"{name}[{i}] has no faces")
        if not np.all(np.isfinite(mesh.vertices)):
            raise ValueError(f"{name}[{i}] has non-finite vertices")
    return meshes
