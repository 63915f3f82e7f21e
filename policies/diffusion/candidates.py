"""Where Diffusion-Suction decodes: the observed depth image's points in the bin, more than the cloud it encodes.

The encoder reads ``num_points`` points (4,096 in the shipped preset), but a suction candidate can sit on any pixel
the camera returned. Cao's heatmap ranks 19,200 pixels at 160 x 120; decoding only at the encoded points leaves
Diffusion-Suction a sparser choice (docs/diffusion.md). The PointNet++ encoder's finest feature propagation
interpolates to any point, so the decoder can score a denser set without retraining.

The image is read at the training split's resolution: a wider one (the env renders 640 x 480) is strided down to it
first. Normals come from the camera module's image-window PCA (``organized_normals``, about 30 neighbours, none
across a depth jump): on the 64 test scenes its Top-50 AP is level with the k-NN estimate the dataset stores (-0.23
[-0.81, 0.31]) at under a third of the cost (36 against 121 ms for 16,384 candidates of a 640 x 480 view, 2 threads,
computed on the candidates' bounding box).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.camera.normals import organized_normals
from policies.diffusion.neighbourhood import grid_sample
from policies.heatmap import pixels_to_world
from policies.observation import camera, depth_image, in_box, workspace

WHO = "Diffusion-Suction's depth candidates"
MAX_WIDTH = 320  # px: the training split's images (eval/report/splits.py); wider depth images are strided down to it


def strided_view(depth: np.ndarray, intrinsics: np.ndarray, max_width: int = MAX_WIDTH
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Every s-th pixel of ``depth`` in both directions, s the least stride to at most ``max_width`` columns, and the
    intrinsics that project it: pixel (r, c) of the result is pixel (s r, s c) of the original, to the bit."""
    stride = max(1, math.ceil(depth.shape[1] / max_width))
    if stride == 1:
        return depth, intrinsics
    scaled = np.array(intrinsics, dtype=np.float64)
    scaled[:2] /= stride  # fx, skew, cx / fy, cy: u = s u' -> (u' - cx / s) / (fx / s)
    return depth[::stride, ::stride], scaled


def has_depth_view(obs: Mapping[str, Any], info: Mapping[str, Any] | None) -> bool:
    """Whether the observation carries what :func:`depth_candidates` reads: a depth image, the camera and the bin."""
    return ("depth" in obs and info is not None and all(info.get(k) is not None
                                                        for k in ("intrinsics", "extrinsics", "workspace")))


def depth_candidates(obs: Mapping[str, Any], info: Mapping[str, Any], count: int) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) float32 points and unit normals, M <= ``count``: the depth image's points inside ``info['workspace']``
    (at most ``MAX_WIDTH`` pixels wide), spatially uniform (``grid_sample``) where there are more. Empty arrays when no
    pixel lies in the bin."""
    if int(count) < 1:
        raise ValueError(f"count must be >= 1, got {count!r}")
    intrinsics, extrinsics = camera(info, WHO)
    depth, intrinsics = strided_view(depth_image(obs, WHO, require_returns=False), intrinsics)
    box = workspace(info, WHO)
    rows, cols = np.nonzero(depth > 0)
    cloud = pixels_to_world(rows, cols, depth, intrinsics, extrinsics)
    at = np.flatnonzero(in_box(cloud, *box)) if box is not None else np.arange(len(cloud))
    if len(at) == 0:
        empty = np.zeros((0, 3), dtype=np.float32)
        return empty, empty.copy()
    if len(at) > count:
        at = at[np.sort(grid_sample(cloud[at], int(count)))]
    # The window estimator on the candidates' bounding box, padded by more than its window: exact there, and the
    # floor around the bin costs nothing
    knn = CameraConfig().normal_knn
    pad = int(math.isqrt(knn)) + 1
    r0, c0 = max(rows[at].min() - pad, 0), max(cols[at].min() - pad, 0)
    r1, c1 = rows[at].max() + pad + 1, cols[at].max() + pad + 1
    image = np.zeros(depth.shape + (3,))
    image[rows, cols] = cloud
    valid = depth > 0
    window = np.zeros_like(valid)
    window[r0:r1, c0:c1] = valid[r0:r1, c0:c1]
    normals = organized_normals(image[r0:r1, c0:c1], window[r0:r1, c0:c1], knn, extrinsics[:3, 3])
    position = np.full(depth.shape, -1, dtype=np.int64)  # pixel -> row of `normals` (organized_normals' order)
    position[np.nonzero(window)] = np.arange(len(normals))
    return cloud[at].astype(np.float32), normals[position[rows[at], cols[at]]].astype(np.float32)
