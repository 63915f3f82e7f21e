"""The surface-segment features the networks read from a batch: lever arms and sizes, in decimetres.

``neighbourhood.model_inputs`` computes them (``policies/surface_segments.py``). The decoder's condition takes the
levers with ``segment_levers`` and the size with ``segment_size``; the encoder's per-point input takes the levers,
and the size with ``segment_size``, under ``levers_in_encoder``.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from policies.diffusion.config import DiffusionConfig
from policies.surface_segments import LEVER_CHANNELS, LEVER_UNIT, SIZE_CHANNELS


def _keys(config: DiffusionConfig, where: str) -> tuple[str, ...]:
    if where == "decoder":
        levers, size = config.segment_levers, config.segment_size
    else:
        levers, size = config.levers_in_encoder, config.levers_in_encoder and config.segment_size
    return (("surface_levers",) if levers else ()) + (("surface_size",) if size else ())


def segment_channels(config: DiffusionConfig, where: str) -> int:
    """How many segment channels the ``where`` ('encoder' | 'decoder') input gains."""
    widths = {"surface_levers": LEVER_CHANNELS, "surface_size": SIZE_CHANNELS}
    return sum(widths[key] for key in _keys(config, where))


def segment_features(batch: Mapping[str, torch.Tensor], config: DiffusionConfig, where: str,
                     dtype: torch.dtype) -> list[torch.Tensor]:
    """The ``where`` input's segment features, (B, N, C) each, in decimetres; a clear error if one is missing."""
    out = []
    for key in _keys(config, where):
        if key not in batch:
            raise KeyError(f"this model's {where} reads {key!r}; build inputs with neighbourhood.model_inputs")
        out.append(batch[key].to(dtype) / LEVER_UNIT)
    return out
