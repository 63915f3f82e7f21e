"""A cheap AP proxy for validation: precision of the top-k predicted points against their label scores."""

from __future__ import annotations

import torch

THRESHOLDS = (0.2, 0.4, 0.6, 0.8)


def topk_precision(pred: torch.Tensor, labels: torch.Tensor, k: int = 50,
                   thresholds: tuple[float, ...] = THRESHOLDS) -> float:
    """Mean over scenes, k' = 1..k and thresholds of #{top-k' predictions with label quality >= theta} / k'.

    ``pred`` (B, N) predicted scores, ``labels`` (B, N) label quality (product of the channels). Same shape as the
    offline AP but on the labelled points, without NMS: a validation signal, not the paper's metric.
    """
    if pred.shape != labels.shape or pred.dim() != 2:
        raise ValueError(f"need pred and labels of the same (B, N) shape, got {pred.shape} and {labels.shape}")
    k = min(k, pred.shape[1])
    top = pred.topk(k, dim=1).indices
    q = labels.gather(1, top)  # (B, k)
    th = torch.tensor(thresholds, dtype=q.dtype, device=q.device)
    hits = (q.unsqueeze(-1) >= th).float().cumsum(dim=1)  # (B, k, T)
    ranks = torch.arange(1, k + 1, device=q.device, dtype=q.dtype).reshape(1, -1, 1)
    return float((hits / ranks).mean())
