"""Diffusion-Suction: a point cloud encoder run once, and a PCDB decoder that denoises a per-point score map."""

from __future__ import annotations

from typing import Mapping

import torch
from torch import nn

from policies.diffusion.config import DiffusionConfig
from policies.diffusion.pcdb import PCDB
from policies.diffusion.pointnet2 import build_encoder, gather
from policies.diffusion.scheduler import DiffusionSchedule
from policies.diffusion.segment_inputs import segment_channels, segment_features


def check_draws(draws: int) -> int:
    """``draws`` as an int, or ValueError: the number of noise draws ``DiffusionSuction.sample`` averages."""
    if int(draws) != draws or draws < 1:
        raise ValueError(f"draws must be an integer >= 1, got {draws!r}")
    return int(draws)


class DiffusionSuction(nn.Module):
    def __init__(self, config: DiffusionConfig):
        super().__init__()
        self.config = config
        self.encoder = build_encoder(config)
        self.encode_width: int = self.encoder.out_channels + segment_channels(config, "decoder")  # encode()'s F
        self.decoder = PCDB(self.encode_width, config.num_channels, config.decoder_dim, config.head_hidden,
                            config.attention_ratio)
        self.scheduler = DiffusionSchedule.from_config(config)

    # -- score <-> diffusion space -------------------------------------------------------------------------------
    def to_signal(self, scores: torch.Tensor) -> torch.Tensor:
        """[0, 1] scores -> x0_bar = (s*2 - 1) * scale."""
        return (scores * 2.0 - 1.0) * self.config.scale

    def to_scores(self, x: torch.Tensor) -> torch.Tensor:
        return (x / (2.0 * self.config.scale) + 0.5).clamp(0.0, 1.0)

    # -- networks -------------------------------------------------------------------------------------------------
    def encode(self, batch: Mapping[str, torch.Tensor], rows: torch.Tensor | None = None) -> torch.Tensor:
        """Per-point condition features (B, N, F); run once per scene. With ``segment_levers`` / ``segment_size``
        the last channels are the batch's ``surface_levers`` / ``surface_size`` (``segment_inputs``).
        ``rows`` (B, M): only those points' features, (B, M, F), as ``sample(point_index=rows)`` would read them,
        for less work (the encoder's finest level runs on those rows alone)."""
        features = self.encoder(batch, rows)
        extra = segment_features(batch, self.config, "decoder", features.dtype)
        if rows is not None:
            extra = [gather(e, rows) for e in extra]
        return torch.cat([features, *extra], dim=-1) if extra else features

    def _denoise_loop(self, cond: torch.Tensor, steps: int, generator: torch.Generator | None,
                      trajectory: list[torch.Tensor] | None = None) -> torch.Tensor:
        b, _, n = cond.shape
        x = torch.randn((b, self.config.num_channels, n), generator=generator, device=cond.device, dtype=cond.dtype)
        if trajectory is not None:
            trajectory.append(self.to_scores(x).transpose(1, 2))
        x0 = x
        for t in self.scheduler.timesteps(steps).tolist():
            out = self.decoder(x, torch.full((1,), t, device=cond.device, dtype=torch.long), cond)
            x, x0 = self.scheduler.step(out, t, x, steps, generator)
            if trajectory is not None:
                trajectory.append(self.to_scores(x).transpose(1, 2))
        if trajectory is not None:  # the run's answer; x_prev already is, unless diffusers stops at t = 0 (see step)
            trajectory[-1] = self.to_scores(x0).transpose(1, 2)
        return x0

    def sample(self, features: torch.Tensor, steps: int | None = None, generator: torch.Generator | None = None,
               return_trajectory: bool = False, point_index: torch.Tensor | None = None, draws: int = 1
               ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """DDIM-sample scores (B, N, C) in [0, 1] from cached encoder features (B, N, F).

        ``point_index`` (B, M) denoises only those points (a uniform subset is enough to rank candidates).
        ``draws`` > 1 averages the score maps of that many noise draws, denoised as one batch (the encoder's
        features are shared): each draw is one sample of the learnt distribution, their mean an estimate of
        its expected score. With ``return_trajectory`` also returns the maps after each step, (steps + 1, B, N,
        C), noise first (of the first draw).
        """
        draws = check_draws(draws)
        if point_index is not None:
            features = gather(features, point_index)
        batch = features.shape[0]
        cond = self.decoder.embed_condition(features.repeat(draws, 1, 1) if draws > 1 else features)
        trajectory: list[torch.Tensor] | None = [] if return_trajectory else None
        x = self._denoise_loop(cond, steps or self.config.inference_steps, generator, trajectory)
        scores = self.to_scores(x).transpose(1, 2)
        if draws > 1:
            scores = scores.reshape(draws, batch, *scores.shape[1:]).mean(0)
        if return_trajectory:
            return scores, torch.stack(trajectory)[:, :batch]
        return scores

    def forward_train(self, batch: Mapping[str, torch.Tensor], generator: torch.Generator | None = None
                      ) -> dict[str, torch.Tensor]:
        """Losses for one batch: denoising loss at a random t, plus the public code's loss on the fully sampled map."""
        cfg = self.config
        labels = batch["labels"][..., : cfg.num_channels]
        x0 = self.to_signal(labels).transpose(1, 2)  # (B, C, N)
        cond = self.decoder.embed_condition(self.encode(batch))
        b = x0.shape[0]
        t = torch.randint(0, cfg.train_steps, (b,), generator=generator, device=x0.device)
        noise = torch.randn(x0.shape, generator=generator, device=x0.device, dtype=x0.dtype)
        out = self.decoder(self.scheduler.add_noise(x0, noise, t), t, cond)
        target = noise if cfg.prediction == "eps" else x0
        # Good suction points are rare (1% of wrench labels exceed 0.5): weighting by the label keeps the loss
        # from being won by predicting 'bad' everywhere. positive_weight = 0 is the plain MSE.
        weight = 1.0 + cfg.positive_weight * labels.transpose(1, 2)
        losses = {"denoise": (weight * (out - target) ** 2).mean()}
        if cfg.map_loss_weight > 0:
            sampled = self._denoise_loop(cond, cfg.inference_steps, generator)
            losses["map"] = (weight * (sampled - x0) ** 2).mean()
            losses["loss"] = losses["denoise"] + cfg.map_loss_weight * losses["map"]
        else:
            losses["loss"] = losses["denoise"]
        return losses


def build_model(config: DiffusionConfig, seed: int = 0) -> DiffusionSuction:
    """Model with weights initialised from ``seed`` without touching the global torch RNG."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return DiffusionSuction(config)
