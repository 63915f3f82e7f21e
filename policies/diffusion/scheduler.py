"""Noise schedule, forward noising and deterministic DDIM (eta = 0), diffusers-compatible, with no module state."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch


def make_betas(num_train_steps: int, schedule: str = "linear", beta_start: float = 1e-4,
               beta_end: float = 0.02) -> torch.Tensor:
    """float64 betas: 'linear' as the public code (diffusers default), 'cosine' as in the paper (Nichol & Dhariwal)."""
    if num_train_steps <= 0:
        raise ValueError(f"num_train_steps must be > 0, got {num_train_steps}")
    if schedule == "linear":
        return torch.linspace(beta_start, beta_end, num_train_steps, dtype=torch.float64)
    if schedule == "cosine":
        s = 0.008
        t = torch.arange(num_train_steps + 1, dtype=torch.float64) / num_train_steps
        abar = torch.cos((t + s) / (1 + s) * math.pi / 2) ** 2
        return (1 - abar[1:] / abar[:-1]).clamp(max=0.999)
    raise ValueError(f"unknown schedule {schedule!r}; choose 'linear' or 'cosine'")


@dataclass(frozen=True)
class DDIMScheduler:
    num_train_steps: int = 1000
    schedule: str = "linear"
    beta_start: float = 1e-4
    beta_end: float = 0.02
    alphas_cumprod: torch.Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        betas = make_betas(self.num_train_steps, self.schedule, self.beta_start, self.beta_end)
        object.__setattr__(self, "alphas_cumprod", torch.cumprod(1.0 - betas, dim=0))

    def _abar(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """abar_t broadcast to ``like`` (batch first); t < 0 means 'fully denoised' (abar = 1, diffusers' set_alpha_to_one)."""
        t = torch.as_tensor(t, device=self.alphas_cumprod.device).long().reshape(-1)
        abar = torch.where(t >= 0, self.alphas_cumprod[t.clamp(min=0)], torch.ones((), dtype=torch.float64))
        abar = abar.to(device=like.device, dtype=like.dtype)
        return abar.reshape(-1, *([1] * (like.dim() - 1)))

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """q(x_t | x_0) = N(sqrt(abar_t) x0, (1 - abar_t) I); t is (B,) or a scalar."""
        abar = self._abar(t, x0)
        return abar.sqrt() * x0 + (1 - abar).sqrt() * noise

    def timesteps(self, num_inference_steps: int) -> torch.Tensor:
        """Descending DDIM timesteps with diffusers' 'leading' spacing: 20 of 1000 -> 950, 900, ..., 0."""
        if not 0 < num_inference_steps <= self.num_train_steps:
            raise ValueError(f"num_inference_steps must be in [1, {self.num_train_steps}], got {num_inference_steps}")
        ratio = self.num_train_steps // num_inference_steps
        return (torch.arange(num_inference_steps) * ratio).flip(0).long()

    def split(self, model_output: torch.Tensor, t: torch.Tensor, x_t: torch.Tensor,
              prediction: str) -> tuple[torch.Tensor, torch.Tensor]:
        """(x0_pred, eps_pred) from the network output, whichever of the two it predicts."""
        abar = self._abar(t, x_t)
        if prediction == "eps":
            return (x_t - (1 - abar).sqrt() * model_output) / abar.sqrt(), model_output
        if prediction == "x0":
            return model_output, (x_t - abar.sqrt() * model_output) / (1 - abar).sqrt().clamp(min=1e-8)
        raise ValueError(f"unknown prediction {prediction!r}; choose 'eps' or 'x0'")

    def step(self, model_output: torch.Tensor, t: int, prev_t: int, x_t: torch.Tensor,
             prediction: str = "eps") -> tuple[torch.Tensor, torch.Tensor]:
        """One DDIM step (eta = 0) from t to prev_t (< 0 for the final step): returns (x_prev, x0_pred)."""
        x0, eps = self.split(model_output, torch.tensor([t]), x_t, prediction)
        abar_prev = self._abar(torch.tensor([prev_t]), x_t)
        return abar_prev.sqrt() * x0 + (1 - abar_prev).sqrt() * eps, x0

    def prev_timesteps(self, timesteps: torch.Tensor) -> torch.Tensor:
        """The step each DDIM timestep jumps to (-1 after the last)."""
        return torch.cat([timesteps[1:], torch.tensor([-1])])
