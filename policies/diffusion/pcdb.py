"""Pointcloud Conditioned Denoising Block: the light decoder that iterates; the encoder features are cached."""

from __future__ import annotations

import math

import torch
from torch import nn


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding of integer timesteps (B,) -> (B, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t.float().reshape(-1, 1) * freqs.reshape(1, -1)
    emb = torch.cat([torch.sin(args), torch.cos(args)], dim=-1)
    return nn.functional.pad(emb, (0, dim % 2))


class ChannelAttention(nn.Module):
    """CBAM channel attention: shared MLP on average- and max-pooled point features."""

    def __init__(self, channels: int, ratio: int = 16):
        super().__init__()
        self.mlp = nn.Sequential(nn.Conv1d(channels, channels // ratio, 1), nn.ReLU(inplace=True),
                                 nn.Conv1d(channels // ratio, channels, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pooled = torch.cat([x.mean(dim=2, keepdim=True), x.amax(dim=2, keepdim=True)], dim=0)
        a, m = self.mlp(pooled).chunk(2, dim=0)
        return x * torch.sigmoid(a + m)


class SpatialAttention(nn.Module):
    """CBAM spatial attention: mean and max over channels, a point-wise conv, sigmoid.

    Points are unordered, so the conv is 1-wide (as in the public code).
    """

    def __init__(self):
        super().__init__()
        self.conv = nn.Conv1d(2, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = torch.cat([x.mean(dim=1, keepdim=True), x.amax(dim=1, keepdim=True)], dim=1)
        return x * torch.sigmoid(self.conv(s))


class PCDB(nn.Module):
    """Embeds noisy map, timestep and condition; sums them; CBAM; head to C channels with a residual to x_t.

    Channel-first (B, C, N). :meth:`embed_condition` runs once per scene; :meth:`forward` once per DDIM step.
    """

    def __init__(self, cond_dim: int, channels: int = 4, hidden: int = 128, head_hidden: int = 64,
                 ratio: int = 16):
        super().__init__()
        self.noise = nn.Sequential(nn.Conv1d(channels, 64, 1), nn.GroupNorm(4, 64), nn.ReLU(inplace=True),
                                   nn.Conv1d(64, hidden, 1), nn.GroupNorm(4, hidden))
        self.time = nn.Sequential(nn.Linear(hidden, hidden), nn.SiLU(), nn.Linear(hidden, hidden))
        self.cond = nn.Sequential(nn.Conv1d(cond_dim, hidden, 1), nn.GroupNorm(4, hidden), nn.ReLU(inplace=True),
                                  nn.Conv1d(hidden, hidden, 1))
        self.channel_attention = ChannelAttention(hidden, ratio)
        self.spatial_attention = SpatialAttention()
        if head_hidden:
            self.head = nn.Sequential(nn.ReLU(), nn.Conv1d(hidden, head_hidden, 1), nn.GroupNorm(4, head_hidden),
                                      nn.ReLU(inplace=True), nn.Conv1d(head_hidden, channels, 1))
        else:
            self.head = nn.Sequential(nn.ReLU(), nn.Conv1d(hidden, channels, 1))
        self.hidden = hidden

    def embed_condition(self, features: torch.Tensor) -> torch.Tensor:
        """Encoder features (B, N, F) -> (B, hidden, N); cached across denoising steps."""
        return self.cond(features.transpose(1, 2))

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """x_t (B, C, N), t (B,) or scalar, cond (B, hidden, N) -> model output (B, C, N)."""
        temb = self.time(timestep_embedding(t.reshape(-1), self.hidden)).unsqueeze(-1)  # (B or 1, hidden, 1)
        h = self.noise(x_t) + cond + temb
        h = self.spatial_attention(self.channel_attention(h))
        return self.head(h) + x_t
