"""Versioned checkpoints: model weights + config (+ optimizer and step for resuming)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from policies.diffusion.config import DiffusionConfig
from policies.diffusion.model import DiffusionSuction, build_model

FORMAT = "parcelpick-diffusion-suction"
FORMAT_VERSION = 1
DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "checkpoints" / "diffusion_suction.pt"


def save_checkpoint(path: str | os.PathLike, model: DiffusionSuction, optimizer: torch.optim.Optimizer | None = None,
                    step: int = 0, extra: dict[str, Any] | None = None) -> Path:
    """Atomic write (tmp file + rename), so an interrupted run never leaves a corrupt checkpoint."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"format": FORMAT, "version": FORMAT_VERSION, "config": model.config.to_dict(),
               "model": model.state_dict(), "step": int(step), "extra": dict(extra or {})}
    if optimizer is not None:
        payload["optimizer"] = optimizer.state_dict()
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The validated payload; FileNotFoundError if missing, ValueError naming the file for anything malformed."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"Diffusion-Suction checkpoint not found: {path}. Train one with "
            f"`python -m policies.diffusion.train --data DIR --out runs/diffusion` and pass checkpoint=.../best.pt")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # torch raises many types for truncated / foreign files
        raise ValueError(f"cannot read checkpoint {path}: {type(e).__name__}: {e}") from e
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"{path} is not a Diffusion-Suction checkpoint (format tag {FORMAT!r} missing)")
    if payload.get("version") != FORMAT_VERSION:
        raise ValueError(f"{path}: checkpoint format version {payload.get('version')!r}, this code reads "
                         f"version {FORMAT_VERSION}")
    for key in ("config", "model"):
        if key not in payload:
            raise ValueError(f"{path}: checkpoint has no {key!r} entry")
    try:
        payload["config"] = DiffusionConfig.from_dict(payload["config"])
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: invalid config in checkpoint: {e}") from e
    return payload


def load_model(path: str | os.PathLike, map_location: str | torch.device = "cpu",
               expected: DiffusionConfig | None = None, **overrides: Any) -> tuple[DiffusionSuction, dict[str, Any]]:
    """Model (eval mode) from a checkpoint. ``expected`` must match the stored config (ValueError listing the fields
    that differ); ``overrides`` change inference-only fields such as ``decode_points``."""
    payload = load_checkpoint(path, map_location)
    config: DiffusionConfig = payload["config"]
    if expected is not None:
        diff = {k: (v, getattr(config, k)) for k, v in expected.to_dict().items() if getattr(config, k) != v}
        if diff:
            raise ValueError(f"{path}: config mismatch (expected, stored): {diff}")
    inference_only = {"decode_points", "inference_steps"}
    bad = set(overrides) - inference_only
    if bad:
        raise ValueError(f"only {sorted(inference_only)} can be overridden at load time, not {sorted(bad)}")
    if overrides:
        config = DiffusionConfig.from_dict({**config.to_dict(), **overrides})
    model = build_model(config)
    try:
        result = model.load_state_dict(payload["model"], strict=False)
    except RuntimeError as e:  # size mismatches
        raise ValueError(f"{path}: weights do not match the stored config: {e}") from e
    if result.missing_keys or result.unexpected_keys:
        raise ValueError(f"{path}: weights do not match the stored config: missing {result.missing_keys[:5]}, "
                         f"unexpected {result.unexpected_keys[:5]}")
    return model.to(map_location).eval(), payload


def export_weights(src: str | os.PathLike, dst: str | os.PathLike, note: str = "") -> Path:
    """Ship a training checkpoint: the same payload without the optimizer state (a third of the size)."""
    payload = load_checkpoint(src)
    payload.pop("optimizer", None)
    payload["config"] = payload["config"].to_dict()
    payload["extra"] = {**payload.get("extra", {}), "exported_from": str(src), "note": note}
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_suffix(dst.suffix + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, dst)
    return dst


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="Export a training checkpoint's weights for shipping.")
    parser.add_argument("src", help="training checkpoint, e.g. runs/diffusion/last.pt")
    parser.add_argument("dst", nargs="?", default=str(DEFAULT_CHECKPOINT))
    parser.add_argument("--note", default="", help="how it was trained (stored in the checkpoint)")
    args = parser.parse_args()
    print(export_weights(args.src, args.dst, args.note))
