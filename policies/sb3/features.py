"""The observation the PPO baseline sees: a coarse depth image, identical in training and deployment."""

from __future__ import annotations

import numpy as np

DEFAULT_GRID: tuple[int, int] = (12, 16)  # (rows, cols); divides 120x160, 240x320 and 480x640 images


def depth_features(depth: np.ndarray, grid: tuple[int, int] = DEFAULT_GRID, far: float = 3.0) -> np.ndarray:
    """Block-mean pool ``depth`` (H, W) or (H, W, 1) to ``grid`` cells, scaled by ``far`` to [0, 1], flattened."""
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim == 3:
        depth = depth[..., 0]
    rows, cols = grid
    h, w = depth.shape
    if h % rows or w % cols:
        raise ValueError(f"depth {h}x{w} must divide evenly into a {rows}x{cols} grid")
    pooled = depth.reshape(rows, h // rows, cols, w // cols).mean(axis=(1, 3))
    return np.clip(pooled / far, 0.0, 1.0).astype(np.float32).ravel()
