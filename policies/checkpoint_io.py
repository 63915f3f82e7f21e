"""Checkpoint file I/O shared by every learned policy: atomic writes and loads that fail with a clear message.

Each policy keeps its own payload layout (config class, keys); this module owns what they have in common, so a
missing, truncated, foreign or mismatched file gives the same kind of error whichever policy reads it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Iterable

import torch
from torch import nn


def save_atomic(payload: dict[str, Any], path: str | os.PathLike) -> Path:
    """``torch.save`` to a temporary file, then rename: an interrupted write never leaves a corrupt checkpoint."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)
    return path


def read_checkpoint(path: str | os.PathLike, kind: str, train_command: str, *, format_tag: str | None = None,
                    required: Iterable[str] = (), map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The checkpoint's payload dict, validated.

    FileNotFoundError (with ``train_command`` as the fix) when the file is missing; ValueError naming the file when
    it is unreadable, not a dict, carries another ``format_tag`` or lacks a ``required`` key.
    Weights-only loading: a checkpoint can never run code.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{kind} checkpoint not found: {path}; train one with `{train_command}`")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises many types for truncated or foreign files
        raise ValueError(f"{kind} checkpoint {path} is corrupt or not a checkpoint: {type(exc).__name__}: {exc}") from exc
    if not isinstance(payload, dict):
        raise ValueError(f"{kind} checkpoint {path} is corrupt or not a checkpoint: it holds a "
                         f"{type(payload).__name__}, not a dict")
    if format_tag is not None and payload.get("format") != format_tag:
        raise ValueError(f"{path} is not a {kind} checkpoint (format tag {format_tag!r} missing)")
    missing = [key for key in required if key not in payload]
    if missing:
        raise ValueError(f"{kind} checkpoint {path} lacks {missing} entries")
    return payload


def load_weights(model: nn.Module, state_dict: dict[str, Any], path: str | os.PathLike, kind: str) -> nn.Module:
    """Strictly load ``state_dict``; a ValueError naming the file when the weights do not fit the stored config."""
    try:
        result = model.load_state_dict(state_dict, strict=False)
    except RuntimeError as exc:  # shape mismatches
        raise ValueError(f"{kind} checkpoint {path}: weights do not match the stored config: {exc}") from exc
    if result.missing_keys or result.unexpected_keys:
        raise ValueError(f"{kind} checkpoint {path}: weights do not match the stored config: missing "
                         f"{result.missing_keys[:5]}, unexpected {result.unexpected_keys[:5]}")
    return model
