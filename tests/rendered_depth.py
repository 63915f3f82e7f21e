"""Depth images ray-cast from known geometry, for the tests of policies that read the depth image."""

from __future__ import annotations

import numpy as np
import open3d as o3d


def straight_down(focal: float, width: int, height: int, position) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics and camera-to-world pose of an OpenCV camera at ``position`` looking straight down."""
    K = np.array([[focal, 0, width / 2 - 0.5], [0, focal, height / 2 - 0.5], [0, 0, 1.0]])
    cam_to_world = np.eye(4)
    cam_to_world[:3, :3] = np.diag([1.0, -1.0, -1.0])
    cam_to_world[:3, 3] = position
    return K, cam_to_world


def depth_image(scene: o3d.t.geometry.RaycastingScene, K: np.ndarray, cam_to_world: np.ndarray, width: int,
                height: int) -> np.ndarray:
    """Ray-cast depth (z along the optical axis, 0 where nothing is hit) of ``scene`` seen by the camera."""
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        o3d.core.Tensor(K), o3d.core.Tensor(np.linalg.inv(cam_to_world)), width, height)
    t_hit = scene.cast_rays(rays)["t_hit"].numpy()
    z_along_ray = (rays.numpy()[..., 3:] @ cam_to_world[:3, :3])[..., 2]
    return np.where(np.isfinite(t_hit), t_hit * z_along_ray, 0.0).astype(np.float32)
