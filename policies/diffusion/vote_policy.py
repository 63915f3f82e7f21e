"""Diffusion-Suction with centre votes (``diffusion_vote``): the shipped model's score re-weighted by the wrench
about each point's voted parcel centre (``centre_vote.py``). Not in the paper."""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import torch

from policies.diffusion.centre_vote import (DEFAULT_CENTRE_VOTE, CentreVoteHead, cluster_centres, file_sha256,
                                            load_centre_vote, vote_wrench)
from policies.diffusion.checkpoint import DEFAULT_CHECKPOINT
from policies.diffusion.policy import DiffusionSuctionPolicy


class DiffusionCentreVotePolicy(DiffusionSuctionPolicy):
    """``DiffusionSuctionPolicy`` whose ranking score is its channels' product times the wrench score about each
    point's voted centre (each vote averaged with its ``cluster_neighbours`` nearest within ``cluster_radius``)."""

    name = "diffusion_vote"

    def __init__(self, checkpoint: str | os.PathLike | None = None, centre_vote: str | os.PathLike | None = None,
                 centre_head: CentreVoteHead | None = None, **kwargs: Any) -> None:
        """``centre_vote``: the head's checkpoint (default: the shipped one), which must have been trained on
        ``checkpoint``'s features; ``centre_head`` instead uses an in-memory head (tests, with ``model=``)."""
        super().__init__(checkpoint=checkpoint, **kwargs)
        if centre_head is None:
            encoder = checkpoint or DEFAULT_CHECKPOINT
            if kwargs.get("model") is not None:
                raise ValueError("an in-memory model needs an in-memory centre_head (its features match no file)")
            centre_head, _ = load_centre_vote(centre_vote or DEFAULT_CENTRE_VOTE, file_sha256(encoder))
        width = int(self.model.encode_width)
        if centre_head.in_features != width:
            raise ValueError(f"the centre vote head reads {centre_head.in_features} features, the model gives {width}")
        self.centre_head = centre_head.to(self.device).eval()
        self.last_centres: np.ndarray | None = None  # (M, 3) voted and averaged centres of the last decoded points

    def quality(self, points: np.ndarray, normals: np.ndarray, features: torch.Tensor, channel_scores: np.ndarray
                ) -> np.ndarray:
        with torch.inference_mode():
            offsets = self.centre_head(features, torch.from_numpy(np.ascontiguousarray(normals)).to(self.device))
        votes = points.astype(np.float64) + offsets.cpu().numpy().astype(np.float64)
        config = self.centre_head.config
        self.last_centres = cluster_centres(votes, config.cluster_radius, config.cluster_neighbours,
                                            torch.get_num_threads())
        wrench = vote_wrench(points, normals, self.last_centres, config.wrench_definition)
        return super().quality(points, normals, features, channel_scores) * wrench
