"""Diffusion-Suction with the learnt hold check (``diffusion_hold``): of its first few candidates, the one the cell
is likeliest to hold goes first, judged from the observation (``features.hold_features``). Not in the paper.

Among Diffusion-Suction's first six picks on the stacked piles its own score says nothing about which the cell holds
(ROC-AUC 0.41 on held-out rehearsals, docs/hold_check.md), so the hold probability alone orders them; the
candidates after them keep the model's order behind them."""

from __future__ import annotations

import os
from typing import Any, Mapping

import numpy as np

from parcelpick_env.config_checks import require_int
from policies.base import Candidates
from policies.diffusion.policy import DiffusionSuctionPolicy
from policies.hold.features import hold_features
from policies.hold.model import DEFAULT_HOLD, HoldNet, load_hold
from policies.observation import point_cloud, workspace

# The model's first candidates that the hold check orders: as many as the collector rehearses per state, so it judges
# the picks it learnt on (the model's first six pass the tool check in 99% of the collected states).
RERANK = 6


class DiffusionHoldPolicy(DiffusionSuctionPolicy):
    """``DiffusionSuctionPolicy`` whose first ``rerank`` candidates are ordered, and scored, by the hold check's
    probability; ``last_hold`` holds the probabilities in the returned order (1 for the candidates after them)."""

    name = "diffusion_hold"
    default_hold: str = DEFAULT_HOLD  # the hold check taught on this policy's own picks

    def __init__(self, checkpoint: str | os.PathLike | None = None, hold: str | os.PathLike | None = None,
                 hold_net: HoldNet | None = None, rerank: int = RERANK, **kwargs: Any) -> None:
        """``hold``: the hold check's checkpoint (default: ``default_hold``); ``hold_net`` an in-memory one (tests)."""
        require_int("DiffusionHoldPolicy", "rerank", rerank, lo=1)
        self.hold_net = hold_net if hold_net is not None else load_hold(hold or self.default_hold)[0]
        self.rerank = rerank
        self.last_hold = np.zeros(0, dtype=np.float32)
        super().__init__(checkpoint=checkpoint, **kwargs)

    def predict(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None,
                top_k: int = 50) -> Candidates:
        """The model's first ``rerank`` candidates ordered by the hold probability (their score), the rest after
        them in the model's order, with decreasing scores below the least hold."""
        ranked = super().predict(obs, info, top_k=max(top_k, self.rerank))
        if len(ranked) == 0:
            self.last_hold = np.zeros(0, dtype=np.float32)
            return ranked
        n = min(len(ranked), self.rerank)
        points, normals = point_cloud(obs, "the hold check", drop_invalid=True)
        features = hold_features(points, normals, ranked.points[:n], ranked.normals[:n], ranked.scores[:n],
                                 workspace(info, "the hold check"))
        hold = self.hold_net.hold_probability(features)
        by_hold = np.argsort(-hold, kind="stable")
        order = np.concatenate([by_hold, np.arange(n, len(ranked))])[:top_k]
        rest = len(ranked) - n
        below = 0.5 * float(hold.min()) * (1.0 - np.arange(1, rest + 1) / (rest + 1))
        scores = np.concatenate([hold[by_hold], below]).astype(np.float32)[:top_k]
        self.last_hold = np.concatenate([hold[by_hold], np.ones(rest, dtype=np.float32)])[:top_k]
        return Candidates(points=ranked.points[order], normals=ranked.normals[order], scores=scores)
