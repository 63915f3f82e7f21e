"""Diffusion-Suction with centre votes and the hold check (``diffusion_vote_hold``): the votes rank the picks
(``policies.diffusion.vote_policy``), and the hold check orders the first few (``policies.hold.policy``), taught on
the vote policy's own picks rehearsed on the cell's twin. Not in the paper.

The votes lead offline and the hold check in closed loop (docs/hold_check.md); this policy carries both, so one
Diffusion-Suction variant can be read in both tables."""

from __future__ import annotations

import os
from typing import Any

from policies.diffusion.vote_policy import DiffusionCentreVotePolicy
from policies.hold.policy import DiffusionHoldPolicy

DEFAULT_VOTE_HOLD = os.path.join(os.path.dirname(__file__), "checkpoints", "hold_vote.pt")


class DiffusionVoteHoldPolicy(DiffusionHoldPolicy, DiffusionCentreVotePolicy):
    """``DiffusionHoldPolicy`` over ``DiffusionCentreVotePolicy``'s ranking: it takes both parents' arguments
    (``hold``, ``rerank``; ``centre_vote``, ``voters``, ``cluster_neighbours``, ``spread_scale``,
    ``segment_radius``)."""

    name = "diffusion_vote_hold"
    default_hold = DEFAULT_VOTE_HOLD

    def __init__(self, *args: Any, segment_radius: float | None = 0.0, **kwargs: Any) -> None:
        """As the parents, but without vote segments unless ``segment_radius`` is given: on the validation piles they
        cost this policy R_grasp (docs/training.md, 'Vote segments'), and its hold check learnt on picks made
        without them."""
        super().__init__(*args, segment_radius=segment_radius, **kwargs)
