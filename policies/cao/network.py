"""A light fully convolutional RGB-D encoder-decoder (a small U-Net) with two sigmoid heatmaps.

SuctionNet's baseline uses a ResNet-based FCN; this keeps the same idea (per-pixel seal and centre
scores from RGB-D) at a size that trains on a laptop CPU in minutes.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from policies.cao.config import CaoConfig
from policies.cao.targets import nearest_resize

RGB_MEAN, RGB_STD = 0.5, 0.25
MAX_RELIEF = 5.0  # clamp of the normalised depth channel, in units of depth_scale


def prepare_input(rgb: np.ndarray | None, depth: np.ndarray, config: CaoConfig) -> np.ndarray:
    """(``config.input_channels``, h, w) float32 network input from an (H, W, 3) uint8 image and (H, W) metric
    depth: the normalised RGB planes (unless ``config.colour`` is False: then ``rgb`` may be None), then the relief
    plane.

    Depth is made relative to the scene's median depth so the net sees relief, not camera height;
    holes (0) stay 0, i.e. "at the median". Colour is resized with anti-aliasing, depth by nearest pixel.
    """
    out_hw = (config.input_height, config.input_width)
    d = nearest_resize(np.asarray(depth, dtype=np.float32), out_hw)
    valid = d > 0
    relief = np.zeros(out_hw, dtype=np.float32)
    if valid.any():
        relief[valid] = np.clip((d[valid] - np.median(d[valid])) / config.depth_scale, -MAX_RELIEF, MAX_RELIEF)
    if not config.colour:
        return relief[None]
    if rgb is None:
        raise ValueError("this Cao network reads colour (config.colour): an RGB image is required")
    colour = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].float() / 255.0
    if colour.shape[-2:] != out_hw:
        colour = F.interpolate(colour, size=out_hw, mode="bilinear", antialias=True, align_corners=False)
    colour = (colour[0].numpy() - RGB_MEAN) / RGB_STD
    return np.concatenate([colour, relief[None]]).astype(np.float32)


class _DoubleConv(nn.Sequential):
    def __init__(self, cin: int, cout: int) -> None:
        super().__init__(
            nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
        )


class CaoNet(nn.Module):
    """U-Net: ``len(widths)`` levels, ``config.input_channels`` inputs (RGB-D or depth), 2 output logits [seal, centre]."""

    out_channels = 2

    def __init__(self, config: CaoConfig) -> None:
        super().__init__()
        widths = list(config.widths)
        self.in_channels = config.input_channels
        self.encoders = nn.ModuleList()
        cin = self.in_channels
        for w in widths:
            self.encoders.append(_DoubleConv(cin, w))
            cin = w
        self.ups = nn.ModuleList()
        self.decoders = nn.ModuleList()
        for w_skip, w_deep in zip(widths[-2::-1], widths[:0:-1]):
            self.ups.append(nn.ConvTranspose2d(w_deep, w_skip, 2, stride=2))
            self.decoders.append(_DoubleConv(2 * w_skip, w_skip))
        self.head = nn.Conv2d(widths[0], self.out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, h, w) -> (B, 2, h, w) logits; h and w must divide by 2**(levels - 1)."""
        skips = []
        for level, encoder in enumerate(self.encoders):
            x = encoder(x if level == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        for up, decoder, skip in zip(self.ups, self.decoders, skips[-2::-1]):
            x = decoder(torch.cat([up(x), skip], dim=1))
        return self.head(x)
