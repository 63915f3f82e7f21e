"""The hold check's network: a small MLP from a pick's features (``features.FEATURES``) to the probability that the
cell holds it, with the training set's feature scaling stored beside its weights."""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from parcelpick_env.config_checks import require_int, require_positive_ints
from policies.checkpoint_io import load_weights, read_checkpoint, save_atomic
from policies.hold.features import FEATURES

FORMAT = "parcelpick-hold-v1"
TRAIN_COMMAND = "python -m policies.hold.train --data data/hold"
DEFAULT_HOLD = os.path.join(os.path.dirname(__file__), "checkpoints", "hold.pt")


@dataclass(frozen=True)
class HoldNetConfig:
    features: tuple[str, ...] = FEATURES
    hidden: int = 32
    layers: int = 0  # logistic regression: ahead of 1-2 hidden layers on the held-out episodes (docs/hold_check.md)

    def __post_init__(self) -> None:
        if tuple(self.features) != FEATURES:
            raise ValueError(f"HoldNetConfig.features must be {FEATURES} (what hold_features computes), "
                             f"got {tuple(self.features)}")
        require_positive_ints(self, ("hidden",))
        require_int("HoldNetConfig", "layers", self.layers, lo=0)


class HoldNet(nn.Module):
    """Standardised features -> ``layers`` ReLU layers of ``hidden`` -> logit (0 layers: logistic regression)."""

    def __init__(self, config: HoldNetConfig = HoldNetConfig()):
        super().__init__()
        self.config = config
        width = len(config.features)
        self.register_buffer("mean", torch.zeros(width))
        self.register_buffer("std", torch.ones(width))
        layers: list[nn.Module] = []
        for _ in range(config.layers):
            layers += [nn.Linear(width, config.hidden), nn.ReLU()]
            width = config.hidden
        self.net = nn.Sequential(*layers, nn.Linear(width, 1))

    def fit_scaling(self, features: np.ndarray) -> None:
        x = torch.as_tensor(features, dtype=torch.float32)
        self.mean.copy_(x.mean(0))
        self.std.copy_(x.std(0).clamp_min(1e-6))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """(K, F) features -> (K,) logits."""
        return self.net((features - self.mean) / self.std).squeeze(-1)

    @torch.inference_mode()
    def hold_probability(self, features: np.ndarray) -> np.ndarray:
        """(K,) float32 probability that the cell holds each pick."""
        x = torch.as_tensor(np.asarray(features, dtype=np.float32))
        return torch.sigmoid(self(x)).numpy().astype(np.float32)


def save_hold(path: str | os.PathLike, net: HoldNet, metadata: dict[str, Any]) -> None:
    config = asdict(net.config)
    config["features"] = list(config["features"])
    save_atomic({"format": FORMAT, "config": config, "state_dict": net.state_dict(), "metadata": metadata}, path)


def load_hold(path: str | os.PathLike = DEFAULT_HOLD) -> tuple[HoldNet, dict[str, Any]]:
    """The network and its metadata; a clear error for a missing, foreign or mismatched file."""
    payload = read_checkpoint(path, "hold check", TRAIN_COMMAND, format_tag=FORMAT,
                              required=("config", "state_dict", "metadata"))
    config = dict(payload["config"])
    config["features"] = tuple(config.get("features", ()))
    try:
        net = HoldNet(HoldNetConfig(**config))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"hold check checkpoint {path} does not match this code: {exc}") from exc
    load_weights(net, payload["state_dict"], path, "hold check")
    return net.eval(), payload["metadata"]
