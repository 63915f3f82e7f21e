"""Cao et al. (SuctionNet baseline) as a Policy: RGB-D -> seal x centre heatmap -> ranked suctions."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
import torch.nn.functional as F

from policies.base import Candidates, Policy
from policies.cao.config import CaoConfig
from policies.checkpoint_io import load_weights, read_checkpoint
from policies.cao.network import CaoNet, prepare_input
from policies.heatmap import box_filter, grid_topk, pixels_to_candidates, workspace_pixels
from policies.observation import camera, depth_image, point_cloud, rgb_image, workspace

DEFAULT_CHECKPOINT = Path(__file__).with_name("checkpoint.pt")


def load_checkpoint(path: str | os.PathLike) -> tuple[CaoNet, dict[str, Any]]:
    """Rebuild the network from a checkpoint written by ``policies.cao.train``; returns (net, checkpoint)."""
    checkpoint = read_checkpoint(path, "Cao", f"python -m policies.cao.train --data DIR --out {path}",
                                 required=("config", "state_dict"))
    try:
        config = CaoConfig.from_dict(checkpoint["config"])
    except (TypeError, ValueError) as exc:  # another policy's checkpoint (Dex-Net's has other config keys)
        raise ValueError(f"{path} is not a Cao checkpoint: its config does not fit CaoConfig ({exc})") from exc
    net = load_weights(CaoNet(config), checkpoint["state_dict"], path, "Cao")
    return net.eval(), checkpoint


def _observation(obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None, colour: bool
                 ) -> tuple[np.ndarray | None, np.ndarray, np.ndarray, np.ndarray]:
    """Validated (rgb, depth (H, W), intrinsics, extrinsics); a clear ValueError for anything malformed. ``rgb`` is
    None for a network without ``colour``, which never reads it (an observation need not carry it)."""
    depth = depth_image(obs, "Cao policy", require_returns=False)
    rgb = rgb_image(obs, depth.shape, "Cao policy") if colour else None
    K, T = camera(info, "Cao policy")
    return rgb, depth, K, T


class CaoPolicy(Policy):
    """Per-pixel seal and object-centre heatmaps from RGB-D; their product ranks suction points.

    ``checkpoint=None`` loads the checkpoint shipped next to this file. Extraction follows SuctionNet:
    a box filter, the best pixel per grid cell, the top ``grid_top_k`` cells, then NMS and top-k. Pixels outside
    ``info['workspace']`` (when given: the env's bin) are never candidates.
    ``threads``: torch CPU threads for the forward pass (restored afterwards; None keeps torch's
    setting). One is the default: this small net gains little from more, and on a shared, busy CPU
    OpenMP barriers made two threads 7x to 70x slower than one in our measurements.
    """

    name = "cao"

    def __init__(self, checkpoint: str | os.PathLike | None = None, *, threads: int | None = 1) -> None:
        if threads is not None and threads < 1:
            raise ValueError(f"threads must be >= 1 or None, got {threads}")
        self.checkpoint_path = Path(checkpoint) if checkpoint is not None else DEFAULT_CHECKPOINT
        self.net, checkpoint_data = load_checkpoint(self.checkpoint_path)
        self.config = CaoConfig.from_dict(checkpoint_data["config"])
        self.meta: dict[str, Any] = dict(checkpoint_data.get("meta", {}))
        self.threads = threads

    @torch.inference_mode()
    def heatmaps(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> np.ndarray:
        """(2, H, W) float32 [seal, centre] in [0, 1] at the observation's resolution."""
        rgb, depth, _, _ = _observation(obs, info, self.config.colour)
        return self._heatmaps(rgb, depth)

    def _heatmaps(self, rgb: np.ndarray | None, depth: np.ndarray) -> np.ndarray:
        previous = torch.get_num_threads()
        if self.threads is not None:
            torch.set_num_threads(self.threads)
        try:
            x = torch.from_numpy(prepare_input(rgb, depth, self.config))[None]
            maps = torch.sigmoid(self.net(x))
            if maps.shape[-2:] != depth.shape:
                maps = F.interpolate(maps, size=depth.shape, mode="bilinear", align_corners=False)
        finally:
            torch.set_num_threads(previous)
        return maps[0].numpy()

    def _extraction_sizes(self, width: int) -> tuple[int, int]:
        """Box filter and grid cell scaled from the reference width, so they cover the same patch."""
        scale = width / self.config.reference_width
        box = max(1, int(round(self.config.box_filter * scale))) | 1
        cell = max(1, int(round(self.config.grid_cell * scale)))
        return box, cell

    @torch.inference_mode()
    def predict(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None,
                top_k: int = 50) -> Candidates:
        if top_k < 1:
            raise ValueError(f"top_k must be >= 1, got {top_k}")
        rgb, depth, K, T = _observation(obs, info, self.config.colour)
        seal, centre = self._heatmaps(rgb, depth)
        box, cell = self._extraction_sizes(depth.shape[1])
        score = box_filter(seal * centre, box, valid=workspace_pixels(depth, K, T, workspace(info, "Cao policy")))
        rows, cols, scores = grid_topk(score, cell=cell, top_k=self.config.grid_top_k)
        points = normals = None
        if "points" in obs and "normals" in obs:
            points, normals = point_cloud(obs, "Cao policy")
        return pixels_to_candidates(rows, cols, scores, depth, K, T, cloud_points=points, cloud_normals=normals,
                                    nms_radius=self.config.nms_radius, top_k=top_k)
