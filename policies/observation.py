"""Validated views of an env observation, shared by every policy.

Policies fail with one clear ValueError on a malformed observation (missing key, wrong shape, NaN,
bad calibration) instead of crashing deep inside numpy, Open3D or torch.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np


def check_camera(intrinsics: Any, extrinsics: Any) -> tuple[np.ndarray, np.ndarray]:
    """Validated float64 K (3, 3) and camera-to-world T (4, 4, OpenCV axes)."""
    K = np.asarray(intrinsics, dtype=np.float64)
    T = np.asarray(extrinsics, dtype=np.float64)
    if K.shape != (3, 3) or T.shape != (4, 4):
        raise ValueError(f"intrinsics must be (3, 3) and extrinsics (4, 4), got {K.shape} and {T.shape}")
    if not (np.isfinite(K).all() and np.isfinite(T).all()):
        raise ValueError("intrinsics and extrinsics must be finite")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"intrinsics need positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4):
        raise ValueError("extrinsics rotation block is not orthonormal")
    return K, T


def camera(info: Mapping[str, Any] | None, who: str) -> tuple[np.ndarray, np.ndarray]:
    """The calibration the env puts in ``info``."""
    if info is None or "intrinsics" not in info or "extrinsics" not in info:
        raise ValueError(f"{who} needs info['intrinsics'] (3x3) and info['extrinsics'] (4x4 cam->world)")
    return check_camera(info["intrinsics"], info["extrinsics"])


def check_workspace(box: Any, who: str) -> np.ndarray:
    """Validated float64 world box (2, 3): min corner, then max corner, finite, min < max on every axis."""
    out = np.asarray(box, dtype=np.float64)
    if out.shape != (2, 3) or not np.all(np.isfinite(out)) or np.any(out[0] >= out[1]):
        raise ValueError(f"{who}: workspace must be ((xmin, ymin, zmin), (xmax, ymax, zmax)) with min < max, "
                         f"got {box!r}")
    return out


def in_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Mask over the last axis of ``points`` (..., 3): inside the closed box [lo, hi] on every axis."""
    return np.all((points >= lo) & (points <= hi), axis=-1)


def workspace(info: Mapping[str, Any] | None, who: str) -> np.ndarray | None:
    """The bin box the env puts in ``info['workspace']``, validated; None when the caller gives none."""
    if info is None or info.get("workspace") is None:
        return None
    return check_workspace(info["workspace"], who)


def depth_image(obs: Mapping[str, Any], who: str, require_returns: bool = True) -> np.ndarray:
    """``obs['depth']`` as float32 (H, W): finite, non-negative, 0 where the sensor returned nothing."""
    if "depth" not in obs:
        raise ValueError(f"{who} needs obs['depth']")
    depth = np.asarray(obs["depth"], dtype=np.float32)
    if depth.ndim == 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    if depth.ndim != 2 or min(depth.shape) < 2:
        raise ValueError(f"obs['depth'] must be (H, W) or (H, W, 1), got {np.shape(obs['depth'])}")
    if not np.isfinite(depth).all():
        raise ValueError("obs['depth'] contains NaN or inf; missing returns must be 0")
    if (depth < 0).any():
        raise ValueError("obs['depth'] has negative values")
    if require_returns and not (depth > 0).any():
        raise ValueError("obs['depth'] is empty (no valid depth returns)")
    return depth


def rgb_image(obs: Mapping[str, Any], shape: tuple[int, int], who: str) -> np.ndarray:
    """``obs['rgb']`` as uint8 (H, W, 3), matching the depth image's ``shape``."""
    if "rgb" not in obs:
        raise ValueError(f"{who} needs obs['rgb']")
    rgb = np.asarray(obs["rgb"])
    if rgb.shape != tuple(shape) + (3,):
        raise ValueError(f"obs['rgb'] must be {tuple(shape) + (3,)} to match the depth image, got {rgb.shape}")
    if rgb.dtype != np.uint8:
        raise ValueError(f"obs['rgb'] must be uint8, got {rgb.dtype}")
    return rgb


def point_cloud(obs: Mapping[str, Any], who: str, drop_invalid: bool = False,
                dtype: type = np.float64) -> tuple[np.ndarray, np.ndarray]:
    """``obs['points']`` and ``obs['normals']`` (N, 3). ``drop_invalid`` removes rows with NaN/inf
    (camera dropouts) instead of rejecting the observation."""
    if "points" not in obs or "normals" not in obs:
        raise ValueError(f"{who} needs obs['points'] and obs['normals'], got keys {sorted(obs)}")
    points = np.asarray(obs["points"], dtype=dtype)
    normals = np.asarray(obs["normals"], dtype=dtype)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"obs['points'] and obs['normals'] must both be (N, 3), got {points.shape} and "
                         f"{normals.shape}")
    finite = np.isfinite(points).all(axis=1) & np.isfinite(normals).all(axis=1)
    if drop_invalid:
        return points[finite], normals[finite]
    if not finite.all():
        raise ValueError("obs['points'] or obs['normals'] contains NaN or inf")
    return points, normals
