"""Centre vote heads with known votes, for the tests of the policies that use them."""

from __future__ import annotations

import math

import torch

from policies.diffusion.centre_vote import CentreVoteConfig, CentreVoteHead
from policies.surface_segments import LEVER_UNIT


def constant_head(in_features: int, offset_m: tuple[float, float, float], spread_m: float = 0.0,
                  segment_spacings: float = 0.0) -> CentreVoteHead:
    """A head that votes every point's centre at ``offset_m`` from it (no clustering: a tiny radius; no vote
    segments unless ``segment_spacings`` > 0), with the error ``spread_m`` per axis (0: the wrench about the voted
    centre alone, ``spread_scale=0``)."""
    config = CentreVoteConfig(hidden=(4,), spread_hidden=(4,), cluster_radius=1e-9, spread_scale=1.0 if spread_m else 0.0,
                              segment_spacings=segment_spacings)
    head = CentreVoteHead(in_features, config)
    with torch.no_grad():
        for p in head.parameters():
            p.zero_()
        head.mlp[-1].bias.copy_(torch.tensor(offset_m) / LEVER_UNIT)
        head.spread[-1].bias.fill_(math.log(spread_m / LEVER_UNIT) if spread_m else 0.0)
    return head.eval()
