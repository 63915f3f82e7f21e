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
    ``segment_spacings``, ``model_wrench``)."""

    name = "diffusion_vote_hold"
    default_hold = DEFAULT_VOTE_HOLD

    def __init__(self, *args: Any, segment_spacings: float | None = 0.0, model_wrench: bool | None = True,
                 **kwargs: Any) -> None:
        """As the parents, but ranked as its hold check learnt (on picks made without vote segments, and scored with
        the model's wrench channel beside the votes') unless ``segment_spacings`` or ``model_wrench`` is given: on the
        validation piles the segments cost this policy R_grasp (docs/training.md, 'Vote segments')."""
        super().__init__(*args, segment_spacings=segment_spacings, model_wrench=model_wrench, **kwargs)
