"""Batched, rotated depth crops around suction candidates (the GQ-CNN input).

Every crop covers the same metric square at its candidate's depth, is rotated so the projection of the
approach axis points along the crop's +x (column) axis, and holds depth relative to the candidate.
All crops of any number of depth images come from one ``grid_sample`` call: the images are stacked
into a tall mosaic with a blank row between them, so bilinear taps never mix two images.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from .config import DexNetConfig


class DepthMosaic:
    """Depth images (B, H, W) in metres (0 = no return), prepared once for repeated cropping."""

    def __init__(self, depth: np.ndarray | torch.Tensor):
        d = torch.as_tensor(np.asarray(depth, dtype=np.float32) if not torch.is_tensor(depth) else depth,
                            dtype=torch.float32)
        if d.ndim == 2:
            d = d[None]
        if d.ndim != 3 or d.shape[1] < 2 or d.shape[2] < 2:
            raise ValueError(f"depth must be (H, W) or (B, H, W) with H, W >= 2, got {tuple(d.shape)}")
        if not torch.isfinite(d).all():
            raise ValueError("depth contains NaN or inf; use 0 for pixels without a return")
        self.num_images, self.height, self.width = (int(s) for s in d.shape)
        valid = (d > 0).float()
        gap = torch.zeros(self.num_images, 1, self.width)
        stacked = torch.stack([torch.cat([d * valid, gap], 1), torch.cat([valid, gap], 1)], 0)  # (2, B, H+1, W)
        self.mosaic = stacked.reshape(1, 2, self.num_images * (self.height + 1), self.width)

    def crops(self, centers_uv: np.ndarray | torch.Tensor, center_depth: np.ndarray | torch.Tensor,
              image_angle: np.ndarray | torch.Tensor, fx: np.ndarray | torch.Tensor | float,
              fy: np.ndarray | torch.Tensor | float, config: DexNetConfig,
              image_index: np.ndarray | torch.Tensor | None = None) -> torch.Tensor:
        """(M, 2, S, S) crops: channel 0 re-centred, scaled, clipped depth (0 where invalid); 1 validity.

        ``centers_uv`` (M, 2) are pixel coordinates (u = column, v = row); ``center_depth`` (M,) the
        candidates' camera z; ``image_angle`` (M,) the approach axis' in-image angle; ``fx``/``fy`` the
        focal lengths (scalar or per crop); ``image_index`` (M,) which image each crop comes from.
        """
        uv = torch.as_tensor(np.asarray(centers_uv) if not torch.is_tensor(centers_uv) else centers_uv,
                             dtype=torch.float32).reshape(-1, 2)
        m = uv.shape[0]
        z = torch.as_tensor(center_depth, dtype=torch.float32).reshape(-1)
        angle = torch.as_tensor(image_angle, dtype=torch.float32).reshape(-1)
        fx_t = torch.as_tensor(fx, dtype=torch.float32).reshape(-1).expand(m)
        fy_t = torch.as_tensor(fy, dtype=torch.float32).reshape(-1).expand(m)
        idx = (torch.zeros(m, dtype=torch.long) if image_index is None
               else torch.as_tensor(image_index, dtype=torch.long).reshape(-1))
        if not (z.shape[0] == angle.shape[0] == idx.shape[0] == m):
            raise ValueError("centers_uv, center_depth, image_angle and image_index must have the same length")
        if m and (idx.min() < 0 or idx.max() >= self.num_images):
            raise ValueError(f"image_index out of range 0..{self.num_images - 1}")
        if m and not (torch.isfinite(uv).all() and torch.isfinite(angle).all() and (z > 0).all()):
            raise ValueError("crop centres and angles must be finite and centre depths > 0")
        s = config.crop_size
        if m == 0:
            return torch.zeros(0, 2, s, s)

        # One affine map per crop from normalised crop coordinates to normalised mosaic coordinates:
        # crop offset (a, b) in metres, rotated by the angle, becomes (fx a', fy b') / z pixels.
        rows = self.num_images * (self.height + 1)
        half = 0.5 * config.crop_metric_size
        kx = (2.0 / self.width) * half * fx_t / z
        ky = (2.0 / rows) * half * fy_t / z
        cos, sin = torch.cos(angle), torch.sin(angle)
        v0 = uv[:, 1] + idx * (self.height + 1)
        theta = torch.stack([torch.stack([kx * cos, -kx * sin, (2 * uv[:, 0] + 1) / self.width - 1], 1),
                             torch.stack([ky * sin, ky * cos, (2 * v0 + 1) / rows - 1], 1)], 1)
        grid = F.affine_grid(theta, [m, 2, s, s], align_corners=False)
        if self.num_images > 1:
            # Rows outside their own image would read a neighbour: send them to the blank gap row above it.
            own_row = ((grid[..., 1] + 1) * rows - 1) / 2 - (idx * (self.height + 1))[:, None, None]
            outside = (own_row <= -1) | (own_row >= self.height)
            gap = ((2 * (idx * (self.height + 1) - 1) + 1) / rows - 1).to(grid.dtype)[:, None, None]
            grid[..., 1] = torch.where(outside, gap.expand_as(own_row), grid[..., 1])
        sampled = F.grid_sample(self.mosaic, grid.reshape(1, m * s, s, 2), mode="bilinear",
                                padding_mode="zeros", align_corners=False)[0].reshape(2, m, s, s)
        weight = sampled[1]
        valid = weight > 0.5
        depth = sampled[0] / weight.clamp_min(1e-6)
        rel = ((depth - z[:, None, None]) / config.depth_scale).clamp(-config.depth_clip, config.depth_clip)
        rel = torch.where(valid, rel, torch.zeros_like(rel))
        return torch.stack([rel, valid.float()], dim=1)


def extract_crops(depth: np.ndarray | torch.Tensor, centers_uv: np.ndarray, center_depth: np.ndarray,
                  image_angle: np.ndarray, fx: float, fy: float, config: DexNetConfig) -> torch.Tensor:
    """Crops from a single depth image (H, W); see ``DepthMosaic.crops``."""
    return DepthMosaic(depth).crops(centers_uv, center_depth, image_angle, fx, fy, config)
