"""Versioned checkpoints: model weights + config (+ optimizer and step for resuming)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from policies.checkpoint_io import load_weights, read_checkpoint, save_atomic
from policies.diffusion.config import DiffusionConfig
from policies.diffusion.model import DiffusionSuction, build_model

FORMAT = "parcelpick-diffusion-suction"
FORMAT_VERSION = 1
DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "checkpoints" / "diffusion_suction.pt"
TRAIN_COMMAND = "python -m policies.diffusion.train --data DIR --out runs/diffusion"


def save_checkpoint(path: str | os.PathLike, model: DiffusionSuction, optimizer: torch.optim.Optimizer | None = None,
                    step: int = 0, extra: dict[str, Any] | None = None) -> Path:
    """Atomic write (tmp file + rename), so an interrupted run never leaves a corrupt checkpoint."""
    payload = {"format": FORMAT, "version": FORMAT_VERSION, "config": model.config.to_dict(),
               "model": model.state_dict(), "step": int(step), "extra": dict(extra or {})}
    if optimizer is not None:
        payload["optimizer"] = optimizer.state_dict()
    return save_atomic(payload, path)


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The validated payload; FileNotFoundError if missing, ValueError naming the file for anything malformed."""
    payload = read_checkpoint(path, "Diffusion-Suction", TRAIN_COMMAND, format_tag=FORMAT, required=("config", "model"),
                              map_location=map_location)
    if payload.get("version") != FORMAT_VERSION:
        raise ValueError(f"{path}: checkpoint format version {payload.get('version')!r}, this code reads "
                         f"version {FORMAT_VERSION}")
    try:
        payload["config"] = DiffusionConfig.from_dict(payload["config"])
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: invalid config in checkpoint: {e}") from e
    return payload


def load_model(path: str | os.PathLike, map_location: str | torch.device = "cpu",
               expected: DiffusionConfig | None = None, **overrides: Any) -> tuple[DiffusionSuction, dict[str, Any]]:
    """Model (eval mode) from a checkpoint. ``expected`` must match the stored config (ValueError listing the fields
    that differ); ``overrides`` change inference-only fields such as ``decode_points`` or the DDIM sampler's."""
    payload = load_checkpoint(path, map_location)
    config: DiffusionConfig = payload["config"]
    if expected is not None:
        diff = {k: (v, getattr(config, k)) for k, v in expected.to_dict().items() if getattr(config, k) != v}
        if diff:
            raise ValueError(f"{path}: config mismatch (expected, stored): {diff}")
    inference_only = {"decode_points", "inference_steps", "timestep_spacing", "eta"}
    bad = set(overrides) - inference_only
    if bad:
        raise ValueError(f"only {sorted(inference_only)} can be overridden at load time, not {sorted(bad)}")
    if overrides:
        config = DiffusionConfig.from_dict({**config.to_dict(), **overrides})
    model = load_weights(build_model(config), payload["model"], path, "Diffusion-Suction")
    return model.to(map_location).eval(), payload


def export_weights(src: str | os.PathLike, dst: str | os.PathLike, note: str = "") -> Path:
    """Ship a training checkpoint: the same payload without the optimizer state (a third of the size)."""
    payload = load_checkpoint(src)
    payload.pop("optimizer", None)
    payload["config"] = payload["config"].to_dict()
    payload["extra"] = {**payload.get("extra", {}), "exported_from": str(src), "note": note}
    return save_atomic(payload, dst)


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="Export a training checkpoint's weights for shipping.")
    parser.add_argument("src", help="training checkpoint, e.g. runs/diffusion/last.pt")
    parser.add_argument("dst", nargs="?", default=str(DEFAULT_CHECKPOINT))
    parser.add_argument("--note", default="", help="how it was trained (stored in the checkpoint)")
    args = parser.parse_args()
    print(export_weights(args.src, args.dst, args.note))
