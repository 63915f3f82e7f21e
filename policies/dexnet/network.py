"""A small GQ-CNN-like suction quality network: depth crop + candidate pose features -> quality."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import nn

from policies.checkpoint_io import load_weights, read_checkpoint, save_atomic

from .config import DexNetConfig

NUM_POSE_FEATURES = 2  # normalised candidate depth, approach tilt from vertical (radians)


class SuctionQualityNet(nn.Module):
    """Strided conv stack over the (depth, validity) crop; the pose features join at the first FC layer,
    as in GQ-CNN's separate pose stream. ``forward`` returns logits; ``quality`` the sigmoid in [0, 1]."""

    def __init__(self, config: DexNetConfig):
        super().__init__()
        self.config = config
        layers: list[nn.Module] = []
        in_ch = 2
        for i, out_ch in enumerate(config.conv_channels):
            kernel = 5 if i == 0 else 3
            layers += [nn.Conv2d(in_ch, out_ch, kernel, stride=2, padding=kernel // 2, bias=False),
                       nn.BatchNorm2d(out_ch), nn.ReLU(inplace=True)]
            in_ch = out_ch
        self.features = nn.Sequential(*layers)
        side = config.crop_size // (2 ** len(config.conv_channels))
        self.head = nn.Sequential(
            nn.Linear(in_ch * side * side + NUM_POSE_FEATURES, config.fc_width), nn.ReLU(inplace=True),
            nn.Linear(config.fc_width, 1),
        )

    def pose_features(self, center_depth: torch.Tensor, tilt: torch.Tensor) -> torch.Tensor:
        c = self.config
        return torch.stack([(center_depth - c.depth_feature_mean) / c.depth_feature_std, tilt], dim=1)

    def forward(self, crops: torch.Tensor, center_depth: torch.Tensor, tilt: torch.Tensor) -> torch.Tensor:
        s = self.config.crop_size
        if crops.ndim != 4 or tuple(crops.shape[1:]) != (2, s, s):
            raise ValueError(f"crops must be (M, 2, {s}, {s}), got {tuple(crops.shape)}")
        x = self.features(crops).flatten(1)
        x = torch.cat([x, self.pose_features(center_depth, tilt)], dim=1)
        return self.head(x).squeeze(1)

    @torch.no_grad()
    def quality(self, crops: torch.Tensor, center_depth: torch.Tensor, tilt: torch.Tensor,
                batch_size: int = 512) -> torch.Tensor:
        """Suction quality in [0, 1], evaluated in eval mode in chunks to bound memory."""
        was_training = self.training
        self.eval()
        try:
            out = [torch.sigmoid(self(crops[i:i + batch_size], center_depth[i:i + batch_size],
                                      tilt[i:i + batch_size]))
                   for i in range(0, crops.shape[0], batch_size)]
        finally:
            self.train(was_training)
        return torch.cat(out) if out else torch.zeros(0)


CHECKPOINT_FORMAT = "parcelpick-dexnet-v1"


def save_checkpoint(path: str | Path, model: SuctionQualityNet, metadata: dict[str, Any] | None = None) -> None:
    """Weights plus the DexNetConfig they were trained with, so crops at inference match training."""
    save_atomic({"format": CHECKPOINT_FORMAT, "config": model.config.to_dict(),
                 "state_dict": model.state_dict(), "metadata": dict(metadata or {})}, path)


def load_checkpoint(path: str | Path) -> tuple[SuctionQualityNet, dict[str, Any]]:
    """The network in eval mode and the checkpoint's metadata; clear errors for missing or corrupt files."""
    blob = read_checkpoint(path, "Dex-Net", f"python -m policies.dexnet.train --out {path}",
                           format_tag=CHECKPOINT_FORMAT, required=("config", "state_dict"))
    model = load_weights(SuctionQualityNet(DexNetConfig.from_dict(blob["config"])), blob["state_dict"], path, "Dex-Net")
    model.eval()
    return model, dict(blob.get("metadata", {}))
