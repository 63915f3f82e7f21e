"""Dex-Net 3.0 style suction baseline: a GQ-CNN-like quality network on rotated depth crops, searched by
the cross-entropy method. ``policies.dexnet.policy.DexNetPolicy`` is the policy;
``python -m policies.dexnet.train`` trains the shipped ``checkpoint.pt``."""

from .config import DexNetConfig, TrainConfig

__all__ = ["DexNetConfig", "TrainConfig"]
