"""The noise schedule and DDIM sampler: a thin wrapper over diffusers' ``DDIMScheduler``, config in, tensors out.

diffusers' schedulers keep the step count in mutable state (``set_timesteps``). This wrapper never mutates one after
configuring it: each step count gets its own scheduler, built on first use and cached, so callers see pure functions
of (config, inputs). Nothing is downloaded: the schedulers are built from arguments, never ``from_pretrained``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from diffusers.schedulers.scheduling_ddim import DDIMScheduler

from parcelpick_env.config_checks import require, require_choice
from policies.diffusion.config import DiffusionConfig, TIMESTEP_SPACINGS

BETA_SCHEDULES = {"linear": "linear", "cosine": "squaredcos_cap_v2"}  # config.schedule -> diffusers beta_schedule
PREDICTION_TYPES = {"eps": "epsilon", "x0": "sample"}  # config.prediction -> diffusers prediction_type


@dataclass(frozen=True)
class DiffusionSchedule:
    """Forward noising and DDIM sampling for one model; build it with :meth:`from_config`.

    Sampling never clips the predicted x0 (diffusers' ``clip_sample`` is off) and the last step lands on
    alpha-bar = 1 (``set_alpha_to_one``), so a run ends on the network's x0 prediction.
    """

    train_steps: int
    schedule: str  # 'linear' | 'cosine'
    beta_start: float
    beta_end: float
    prediction: str  # 'eps' | 'x0'
    timestep_spacing: str  # 'leading' | 'trailing' | 'linspace'
    eta: float  # 0 = deterministic DDIM, 1 = DDPM-like noise
    _by_steps: dict[int, DDIMScheduler] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        owner = "DiffusionSchedule"
        require_choice(owner, "schedule", self.schedule, tuple(BETA_SCHEDULES))
        require_choice(owner, "prediction", self.prediction, tuple(PREDICTION_TYPES))
        require_choice(owner, "timestep_spacing", self.timestep_spacing, TIMESTEP_SPACINGS)
        require(0.0 <= self.eta <= 1.0, owner, f"eta must be in [0, 1], got {self.eta}")
        self._by_steps[0] = self._build()  # for add_noise and alphas_cumprod; set_timesteps is never called on it

    @classmethod
    def from_config(cls, config: DiffusionConfig) -> "DiffusionSchedule":
        return cls(config.train_steps, config.schedule, config.beta_start, config.beta_end, config.prediction,
                   config.timestep_spacing, config.eta)

    def _build(self) -> DDIMScheduler:
        return DDIMScheduler(num_train_timesteps=self.train_steps, beta_start=self.beta_start, beta_end=self.beta_end,
                             beta_schedule=BETA_SCHEDULES[self.schedule], clip_sample=False, set_alpha_to_one=True,
                             steps_offset=0, prediction_type=PREDICTION_TYPES[self.prediction],
                             timestep_spacing=self.timestep_spacing)

    def diffusers_scheduler(self, inference_steps: int) -> DDIMScheduler:
        """The cached diffusers scheduler set to ``inference_steps`` (do not call ``set_timesteps`` on it)."""
        if not 0 < inference_steps <= self.train_steps:
            raise ValueError(f"inference_steps must be in [1, {self.train_steps}], got {inference_steps}")
        if inference_steps not in self._by_steps:
            scheduler = self._build()
            scheduler.set_timesteps(inference_steps)
            self._by_steps[inference_steps] = scheduler
        return self._by_steps[inference_steps]

    @property
    def alphas_cumprod(self) -> torch.Tensor:
        """alpha-bar_t for t = 0 .. train_steps - 1 (float32, as diffusers computes it)."""
        return self._by_steps[0].alphas_cumprod

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor | int) -> torch.Tensor:
        """q(x_t | x_0) = N(sqrt(abar_t) x0, (1 - abar_t) I); ``t`` is (B,) for batch-first ``x0``, or a scalar."""
        return self._by_steps[0].add_noise(x0, noise, torch.as_tensor(t, dtype=torch.long).reshape(-1))

    def timesteps(self, inference_steps: int) -> torch.Tensor:
        """The descending timesteps of an ``inference_steps`` run under ``timestep_spacing`` (5 of 1000: 'leading'
        800 .. 0, 'trailing' 999 .. 199, 'linspace' 999 .. 0)."""
        return self.diffusers_scheduler(inference_steps).timesteps.clone()

    def step(self, model_output: torch.Tensor, t: int, x_t: torch.Tensor, inference_steps: int,
             generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """One DDIM step of an ``inference_steps`` run from timestep ``t``: returns (x_prev, x0 prediction).

        ``generator`` draws the step's noise when ``eta`` > 0. diffusers steps from ``t`` to
        ``t - train_steps // inference_steps`` whatever the spacing: for 'linspace' (and 'trailing' when
        ``inference_steps`` does not divide ``train_steps``) that is not the next listed timestep (diffusers #12633).
        """
        x_prev, x0 = self.diffusers_scheduler(inference_steps).step(model_output, int(t), x_t, eta=self.eta,
                                                                    generator=generator, return_dict=False)
        return x_prev, x0
