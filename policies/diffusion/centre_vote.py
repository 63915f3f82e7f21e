"""Centre votes: where the parcel under each observed point has its centre, learnt on the Diffusion-Suction features.

The wrench score is a property of the whole parcel: the torque of its weight about the cup grows with the lever
from the cup to the parcel's centre, which a partial view does not show. Scored about the true surface centroids,
the shipped model's own seal and collision channels reach a Top-50 AP of 78.0 on the test split (the label oracle:
76.2), against 51.2 with its wrench channel; the centroid of a parcel's visible points scores 36.6, the centroid of
its smooth surface segment 40.1 (docs/training.md, 'Centre votes'). So a small head votes, per point, for the
centre from the frozen encoder's features (VoteNet's idea); each vote is averaged with its nearest votes within
``cluster_radius`` of it, and SuctionNet's wrench formula (``wrench_scores``) about that centre re-weights the
model's score. The head reads only the observation's features: no ground truth at inference.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import nn

from parcelpick_env.config_checks import (config_from_dict, config_to_dict, require, require_choice, require_int,
                                          require_positive_numbers)
from parcelpick_env.suction.quality import definition_config
from parcelpick_env.suction.wrench import wrench_scores
from policies.checkpoint_io import load_weights, read_checkpoint, save_atomic
from policies.surface_segments import LEVER_UNIT

FORMAT = "parcelpick-centre-vote"
FORMAT_VERSION = 1
DEFAULT_CENTRE_VOTE = Path(__file__).resolve().parent / "checkpoints" / "centre_vote.pt"
TRAIN_COMMAND = "python -m policies.diffusion.train_centre_vote --data DIR"
# The definitions whose wrench is a closed formula of the lever alone (unit mass): ``physical`` needs the real mass.
VOTE_DEFINITIONS: tuple[str, ...] = ("suctionnet", "paper", "paper_compat")


@dataclass(frozen=True)
class CentreVoteConfig:
    """The vote head's shape and how its votes become a wrench score."""

    hidden: tuple[int, ...] = (256, 256, 128)  # MLP widths on (features, normal)
    cluster_radius: float = 0.04  # m: each vote is averaged with the votes this close (0.02 and 0.04 tried on val)
    cluster_neighbours: int = 64  # ... at most this many, the nearest (itself among them)
    # The votes are cast at this many of the decoded points, evenly spread (0: at every one), and each other point
    # takes its nearest voter's centre: the neighbours' cap then spans the same area at any candidate density
    # (256-1024 level on the validation split, every one of 16,384 2.1 lower; docs/training.md, 'Voters').
    voters: int = 512
    wrench_definition: str = "suctionnet"  # whose wrench formula re-weights the score (VOTE_DEFINITIONS)

    def __post_init__(self) -> None:
        owner = type(self).__name__
        require(isinstance(self.hidden, tuple) and len(self.hidden) > 0, owner,
                f"hidden must be a non-empty tuple of widths, got {self.hidden!r}")
        for width in self.hidden:
            require_int(owner, "hidden widths", width, lo=1)
        require_positive_numbers(self, ("cluster_radius",))
        require_int(owner, "cluster_neighbours", self.cluster_neighbours, lo=1)
        require_int(owner, "voters", self.voters, lo=0)
        require_choice(owner, "wrench_definition", self.wrench_definition, VOTE_DEFINITIONS)

    def to_dict(self) -> dict[str, Any]:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "CentreVoteConfig":
        return config_from_dict(cls, data)


class CentreVoteHead(nn.Module):
    """Per-point MLP: (encoder features, normal) -> offset from the point to its parcel's centre, in metres.

    The inputs are standardised with the training set's statistics (buffers, stored in the checkpoint); the
    output is learnt in ``LEVER_UNIT`` (decimetres), O(1) like the levers the decoder reads."""

    input_mean: torch.Tensor
    input_std: torch.Tensor

    def __init__(self, in_features: int, config: CentreVoteConfig = CentreVoteConfig()) -> None:
        super().__init__()
        require_int(type(self).__name__, "in_features", in_features, lo=1)
        self.config = config
        self.in_features = int(in_features)
        width = self.in_features + 3
        layers: list[nn.Module] = []
        for hidden in config.hidden:
            layers += [nn.Linear(width, hidden), nn.GELU()]
            width = hidden
        layers.append(nn.Linear(width, 3))
        self.mlp = nn.Sequential(*layers)
        self.register_buffer("input_mean", torch.zeros(self.in_features + 3))
        self.register_buffer("input_std", torch.ones(self.in_features + 3))

    def set_standardisation(self, inputs: torch.Tensor) -> None:
        """Standardise with the mean and spread of ``inputs`` (M, in_features + 3), as ``inputs_of`` makes them."""
        self.input_mean.copy_(inputs.mean(0))
        self.input_std.copy_(inputs.std(0) + 1e-3)

    def forward_units(self, inputs: torch.Tensor) -> torch.Tensor:
        """Offsets in ``LEVER_UNIT`` from prepared ``inputs`` (..., in_features + 3): what the training loss reads."""
        return self.mlp((inputs - self.input_mean) / self.input_std)

    def forward(self, features: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        """(..., 3) offsets in metres for per-point ``features`` (..., F) and unit ``normals`` (..., 3)."""
        return self.forward_units(inputs_of(features, normals, self.in_features)) * LEVER_UNIT


def inputs_of(features: torch.Tensor, normals: torch.Tensor, in_features: int) -> torch.Tensor:
    """The head's input rows: the features, then the normal."""
    if features.shape[-1] != in_features or normals.shape[-1] != 3 or features.shape[:-1] != normals.shape[:-1]:
        raise ValueError(f"centre vote head needs features (..., {in_features}) and normals (..., 3) on the same "
                         f"points, got {tuple(features.shape)} and {tuple(normals.shape)}")
    return torch.cat([features.float(), normals.float()], dim=-1)


def cluster_centres(centres: np.ndarray, radius: float, neighbours: int, workers: int = 1) -> np.ndarray:
    """(N, 3) float64: each voted centre averaged with its ``neighbours`` nearest votes within ``radius`` (itself
    among them); ``workers``: the k-NN query's threads (the same neighbours, faster for many votes).

    Votes for one parcel scatter around its centre; their local mean is steadier than any one of them. The cap
    bounds the cost where votes crowd (all pairs within 4 cm on a synthetic pile: 1 million)."""
    centres = np.asarray(centres, dtype=np.float64)
    if centres.ndim != 2 or centres.shape[1] != 3:
        raise ValueError(f"centres must be (N, 3), got {centres.shape}")
    if not radius > 0 or int(neighbours) != neighbours or neighbours < 1:
        raise ValueError(f"need radius > 0 and neighbours >= 1, got {radius}, {neighbours}")
    if len(centres) == 0:
        return centres.copy()
    k = min(int(neighbours), len(centres))
    distances, index = cKDTree(centres).query(centres, k=k, distance_upper_bound=radius, workers=workers)
    distances, index = distances.reshape(len(centres), k), index.reshape(len(centres), k)
    found = np.isfinite(distances)  # beyond the radius: inf distance, index N
    padded = np.vstack([centres, np.zeros((1, 3))])
    return padded[index].sum(axis=1) / found.sum(axis=1, keepdims=True)


def vote_wrench(points: np.ndarray, normals: np.ndarray, centres: np.ndarray, definition: str) -> np.ndarray:
    """(N,) float32: ``definition``'s wrench score of each contact about its voted centre (the shared formula)."""
    require_choice("vote_wrench", "definition", definition, VOTE_DEFINITIONS)
    return wrench_scores(np.asarray(points, dtype=np.float64), np.asarray(normals, dtype=np.float64),
                         np.asarray(centres, dtype=np.float64), definition_config(definition))


def file_sha256(path: str | os.PathLike) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def save_centre_vote(path: str | os.PathLike, head: CentreVoteHead, encoder_sha256: str,
                     extra: dict[str, Any] | None = None) -> Path:
    """Atomic write; ``encoder_sha256`` names the Diffusion-Suction checkpoint whose features the head reads."""
    payload = {"format": FORMAT, "version": FORMAT_VERSION, "config": head.config.to_dict(),
               "in_features": head.in_features, "model": head.state_dict(), "encoder_sha256": str(encoder_sha256),
               "extra": dict(extra or {})}
    return save_atomic(payload, path)


def load_centre_vote(path: str | os.PathLike, encoder_sha256: str | None = None) -> tuple[CentreVoteHead, dict[str, Any]]:
    """The head (eval mode) and its payload. ``encoder_sha256``: the Diffusion-Suction checkpoint it will read
    features from; a head trained on another one's features is refused (ValueError naming both)."""
    payload = read_checkpoint(path, "centre vote", TRAIN_COMMAND, format_tag=FORMAT,
                              required=("config", "in_features", "model", "encoder_sha256"))
    if payload.get("version") != FORMAT_VERSION:
        raise ValueError(f"{path}: centre vote format version {payload.get('version')!r}, this code reads "
                         f"version {FORMAT_VERSION}")
    if encoder_sha256 is not None and payload["encoder_sha256"] != encoder_sha256:
        raise ValueError(f"{path} was trained on the features of the Diffusion-Suction checkpoint with SHA-256 "
                         f"{payload['encoder_sha256'][:12]}..., not this one ({encoder_sha256[:12]}...); retrain it "
                         f"with `{TRAIN_COMMAND} --checkpoint <that checkpoint>`")
    try:
        config = CentreVoteConfig.from_dict(payload["config"])
        head = CentreVoteHead(int(payload["in_features"]), config)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: invalid centre vote config: {e}") from e
    load_weights(head, payload["model"], path, "centre vote")
    return head.eval(), payload
