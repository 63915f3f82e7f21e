"""Where the privileged oracle would push a parcel to part a pile in which no pick holds.

In the 30-parcel heap every parcel left can bear or lean on another; then every pick the oracle rehearses
drags a neighbour and drops, and the episode ends on three failures. One push of the topmost free parcel,
chosen in hindsight, opened most of those dead ends (results/ORACLE.md, 'A parting move'). The oracle tries
the pushes listed here on its twin of the cell (``CellTwin.rehearse_push``) and takes the first after which
one of its picks holds there (``OraclePolicy``, ``parting_pushes``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the oracle imports this module
    from policies.oracle import GroundTruth

# The four pushes per parcel: along the tote's axes (its walls), so that a pushed parcel slides along or away
# from a wall rather than into a corner.
PUSH_DIRECTIONS = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
SIDE_GAP = 0.01  # m between the cup's side and the parcel's bounding box where the tool comes down
BELOW_TOP = 0.03  # m below the parcel's top where the cup pushes ...
ABOVE_BOTTOM = 0.015  # m ... but never lower than this above its bottom (a thin mailer: just above what it lies on)


@dataclass(frozen=True)
class PushCandidate:
    """A parting push: the tool tip comes down to ``start`` and moves along ``direction`` (horizontal, unit)."""

    parcel: int  # row of the parcel it is aimed at
    start: np.ndarray  # (3,)
    direction: np.ndarray  # (3,)


def push_candidates(truth: "GroundTruth", pinned: np.ndarray, cup_radius: float, limit: int,
                    bounds: tuple[np.ndarray, np.ndarray] | None = None) -> list[PushCandidate]:
    """Up to ``limit`` pushes: the parcels nothing rests on first (``pinned`` False), the highest first, then the
    pinned ones, highest first; each pushed from beside its world bounding box in the four ``PUSH_DIRECTIONS``.
    With ``bounds`` (the env's action box, ``BinSpec.workspace``), a start outside it is left out: the env would
    refuse it as an invalid action (beside a parcel against a wall it lies beyond the wall)."""
    heights = truth.coms[:, 2] if len(truth.meshes) else np.zeros(0)
    order = sorted(range(len(truth.meshes)), key=lambda k: (bool(pinned[k]), -float(heights[k])))
    out: list[PushCandidate] = []
    for k in order:
        lo, hi = truth.meshes[k].bounds
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        z = max(float(lo[2]) + ABOVE_BOTTOM, float(hi[2]) - BELOW_TOP)
        for d in PUSH_DIRECTIONS:
            reach = float(np.abs(d[:2]) @ half[:2]) + cup_radius + SIDE_GAP
            start = centre - reach * d
            start[2] = z
            if bounds is not None and (np.any(start < bounds[0]) or np.any(start > bounds[1])):
                continue
            out.append(PushCandidate(k, start, d.copy()))
            if len(out) == limit:
                return out
    return out
