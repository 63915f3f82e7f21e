"""Diffusion-Suction with centre votes (``diffusion_vote``): the shipped model's seal and collision scores times the
wrench about each point's voted parcel centre (``centre_vote.py``), in place of the model's own wrench channel. Not
in the paper."""

from __future__ import annotations

import copy
import dataclasses
import os
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree

from dataset.annotate import LABEL_CHANNELS
from policies.diffusion.centre_vote import (DEFAULT_CENTRE_VOTE, CentreVoteHead, cluster_centres, file_sha256,
                                            load_centre_vote, vote_wrench)
from policies.diffusion.checkpoint import DEFAULT_CHECKPOINT
from policies.diffusion.policy import DiffusionSuctionPolicy
from policies.diffusion.vote_segments import (bin_interior, covered_fraction, median_spacing, top_centres,
                                             vote_segments)
from policies.observation import workspace

WRENCH_CHANNEL = LABEL_CHANNELS.index("wrench")  # the model's score channels follow the labels' columns


class DiffusionCentreVotePolicy(DiffusionSuctionPolicy):
    """``DiffusionSuctionPolicy`` whose ranking score is its channels' product (the wrench channel left out unless
    ``model_wrench``) times the wrench score about each point's voted centre (each vote averaged with its
    ``cluster_neighbours`` nearest within ``cluster_radius``, by their predicted errors; votes cast at ``voters`` of
    the decoded points, the others taking their nearest voter's centre; then, where the votes segment a parcel with a
    visible top, that top's centroid: ``vote_segments.py``), expected over that centre's error."""

    name = "diffusion_vote"

    def __init__(self, checkpoint: str | os.PathLike | None = None, centre_vote: str | os.PathLike | None = None,
                 centre_head: CentreVoteHead | None = None, voters: int | None = None,
                 cluster_neighbours: int | None = None, spread_scale: float | None = None,
                 segment_spacings: float | None = None, model_wrench: bool | None = None, **kwargs: Any) -> None:
        """``centre_vote``: the head's checkpoint (default: the shipped one), which must have been trained on
        ``checkpoint``'s features; ``centre_head`` instead uses an in-memory head (tests, with ``model=``).
        ``voters``, ``cluster_neighbours``, ``spread_scale``, ``segment_spacings``, ``model_wrench``: in place of the
        head's stored ``CentreVoteConfig`` values (they act at inference only; ``--policy-arg voters=0`` votes at
        every decoded point, ``spread_scale=0`` takes the wrench about the averaged centre alone,
        ``segment_spacings=0`` the votes' centres without vote segments, ``model_wrench=true`` keeps the model's
        wrench channel too)."""
        super().__init__(checkpoint=checkpoint, **kwargs)
        if centre_head is None:
            encoder = checkpoint or DEFAULT_CHECKPOINT
            if kwargs.get("model") is not None:
                raise ValueError("an in-memory model needs an in-memory centre_head (its features match no file)")
            centre_head, _ = load_centre_vote(centre_vote or DEFAULT_CENTRE_VOTE, file_sha256(encoder))
        width = int(self.model.encode_width)
        if centre_head.in_features != width:
            raise ValueError(f"the centre vote head reads {centre_head.in_features} features, the model gives {width}")
        overrides = {k: v for k, v in (("voters", voters), ("cluster_neighbours", cluster_neighbours),
                                       ("spread_scale", spread_scale), ("segment_spacings", segment_spacings),
                                       ("model_wrench", model_wrench))
                     if v is not None}
        if overrides:  # on this policy's own copy: a head passed in keeps its config for its other users
            centre_head = copy.copy(centre_head)
            centre_head.config = dataclasses.replace(centre_head.config, **overrides)
        self.centre_head = centre_head.to(self.device).eval()
        self.last_centres: np.ndarray | None = None  # (M, 3) the centres the last decoded points were scored about
        self.last_spread: np.ndarray | None = None  # (M,) their typical predicted error per horizontal axis (m)
        self.last_covered: np.ndarray | None = None  # (M,) the share of each point's parcel under another

    def quality(self, points: np.ndarray, normals: np.ndarray, features: torch.Tensor, channel_scores: np.ndarray,
                info: Mapping[str, Any] | None = None) -> np.ndarray:
        config = self.centre_head.config
        threads = torch.get_num_threads()
        voters = spread_indices(len(points), config.voters)
        voter_points = points[voters]
        with torch.inference_mode():
            at = torch.from_numpy(voters).to(self.device)
            offsets, errors = self.centre_head(
                features[at], torch.from_numpy(np.ascontiguousarray(normals[voters])).to(self.device))
        votes = voter_points.astype(np.float64) + offsets.cpu().numpy().astype(np.float64)
        centres, spread = cluster_centres(votes, config.cluster_radius, config.cluster_neighbours, threads,
                                          errors.cpu().numpy().astype(np.float64))
        if len(voters) < len(points):
            nearest = cKDTree(voter_points).query(points, workers=threads)[1]
            centres, spread = centres[nearest], spread[nearest]
        covered = (self._centre_on_tops(points, normals, centres, spread, info, threads)
                   if config.segment_spacings > 0 else np.zeros(len(points)))
        self.last_centres, self.last_spread, self.last_covered = centres, spread, covered
        wrench = vote_wrench(points, normals, centres, config.wrench_definition,
                             spread * config.spread_scale if config.spread_scale > 0 else None, config.spread_draws)
        if not config.model_wrench:  # the votes' wrench in place of the model's own channel
            channel_scores = np.delete(channel_scores, WRENCH_CHANNEL, axis=1)
        return super().quality(points, normals, features, channel_scores, info) * wrench * (1.0 - covered)

    def _centre_on_tops(self, points: np.ndarray, normals: np.ndarray, centres: np.ndarray, spread: np.ndarray,
                        info: Mapping[str, Any] | None, workers: int = 1) -> np.ndarray:
        """In place: the points of each vote segment with a visible top (``vote_segments.py``) centred on that top,
        with the spread ``segment_shift_spread`` times the top's shift from the segment's mean vote: a whole top's
        centroid misses by millimetres and agrees with its votes, the votes' own error is not its own, and a top
        that sits off its votes (a fragment of a tube, a parcel half seen) is the one to doubt. Returns (N,) the
        share of each point's parcel that lies under another (``covered_fraction``; 0 outside the segments)."""
        config = self.centre_head.config
        covered = np.zeros(len(points))
        inside = np.flatnonzero(bin_interior(points, workspace(info, "Diffusion-Suction's vote segments"),
                                             config.segment_floor_margin, config.segment_wall_margin))
        if len(inside) < 2:  # nothing to segment
            return covered
        # once, in the float64 every step below computes in
        segment_points, votes = points[inside].astype(np.float64), centres[inside]
        tree = cKDTree(segment_points)  # shared by the spacing and the graph
        radius = config.segment_spacings * median_spacing(segment_points, tree, workers)
        if radius == 0:  # every point at one place
            return covered
        labels = vote_segments(segment_points, votes, radius, config.segment_vote_gap, tree)
        tops, found, shift = top_centres(segment_points, normals[inside], labels, config.segment_up_cos,
                                         config.segment_min_points, votes, config.segment_max_shift)
        top_z = np.where(found, tops[:, 2], segment_points[:, 2])
        covered[inside] = covered_fraction(segment_points, labels, votes, top_z, config.segment_cover_margin, workers)
        centres[inside[found]], spread[inside[found]] = tops[found], config.segment_shift_spread * shift[found]
        return covered


def spread_indices(count: int, at_most: int) -> np.ndarray:
    """(min(count, at_most),) int64 indices evenly spread over ``range(count)``, every one where ``at_most`` is 0:
    the depth candidates come in image order, so an even stride covers the view."""
    if at_most == 0 or at_most >= count:
        return np.arange(count)
    return np.linspace(0, count - 1, at_most).round().astype(np.int64)
