"""Centre votes: where the parcel under each observed point has its centre, learnt on the Diffusion-Suction features.

The wrench score is a property of the whole parcel: the torque of its weight about the cup grows with the lever
from the cup to the parcel's centre, which a partial view does not show. Scored about the true surface centroids,
the shipped model's own seal and collision channels reach a Top-50 AP of 78.0 on the test split (the label oracle:
76.2), against 51.2 with its wrench channel; the centroid of a parcel's visible points scores 36.6, the centroid of
its smooth surface segment 40.1 (docs/training.md, 'Centre votes'). So a small head votes, per point, for the
centre from the frozen encoder's features (VoteNet's idea); each vote is averaged with its nearest votes within
``cluster_radius`` of it, and SuctionNet's wrench formula (``wrench_scores``) about that centre re-weights the
model's score. The head reads only the observation's features: no ground truth at inference.

Each vote also carries its predicted error (``spread``, a second MLP on the same inputs, fitted to the first's
residuals): votes are averaged with weights 1/sigma^2, and the score takes the wrench expected over the averaged
centre's typical error (``expected_wrench_scores``), so a pick on a parcel whose centre is uncertain ranks below
one that is known (docs/training.md, 'The vote's spread').
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

from parcelpick_env.config_checks import (config_from_dict, config_to_dict, require, require_choice,
                                          require_finite_numbers, require_int, require_positive_numbers)
from parcelpick_env.suction.quality import definition_config
from parcelpick_env.suction.wrench import expected_wrench_scores, wrench_scores
from policies.checkpoint_io import load_weights, read_checkpoint, save_atomic
from policies.surface_segments import LEVER_UNIT

FORMAT = "parcelpick-centre-vote"
FORMAT_VERSION = 2  # 2: the spread MLP
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
    spread_hidden: tuple[int, ...] = (128, 128)  # MLP widths of the votes' predicted error, on the same inputs
    # The wrench is the mean over centres moved by spread_scale times the averaged votes' typical error (0: about
    # the averaged centre alone), sampled at spread_draws fixed draws (0.5 to 3 tried on validation, 0.75-1.25
    # level; docs/training.md, 'The vote's spread')
    spread_scale: float = 1.0
    spread_draws: int = 16
    # Vote segments (vote_segments.py): decoded points within segment_spacings times their median nearest-neighbour
    # spacing (3.5 mm at the cell's 16,384 candidates) whose voted centres lie within segment_vote_gap are one
    # parcel, centred on its up-facing points (normal z >= segment_up_cos; at least segment_min_points of them, else
    # the votes' centre stands), with a spread of segment_shift_spread times that top's horizontal shift from the
    # segment's mean vote (the two estimates' disagreement; 0: exact). Only points segment_floor_margin above the
    # bin's floor and segment_wall_margin in from its walls are segmented. segment_spacings 0: the votes' centres
    # alone. 1.75-2.5 spacings, 5-15 mm and gaps of 5 cm to 10 m tried on both validation splits (docs/training.md,
    # 'Finer vote segments'); a radius in spacings holds at another candidate density, a fixed one did not.
    segment_spacings: float = 2.0
    segment_vote_gap: float = 0.16  # m
    segment_up_cos: float = 0.9
    segment_min_points: int = 5
    segment_floor_margin: float = 0.003  # m: six times the camera's depth noise, under the thinnest envelope (5 mm)
    segment_wall_margin: float = 0.01  # m
    segment_max_shift: float = 0.04  # m: a top this far from its segment's mean vote (a covered parcel) keeps the votes
    segment_shift_spread: float = 0.5  # 0, 0.5 and 1 tried on both validation splits (docs/training.md)
    # a segment's score is multiplied by 1 - the share of its mirrored points (about its mean vote) that fall under
    # another segment standing this far above its top: a parcel another rests on (vote_segments.covered_fraction)
    segment_cover_margin: float = 0.01  # m
    # Whether the model's own wrench channel stays in the score beside the votes' wrench. False: the votes' wrench
    # replaces it, as eval/centre_bound.py's centres do (+0.8 Top-50 AP on val_novel with 1 cm segments, +1.8 at 7 mm);
    # the hold variant keeps it, its check having learnt on picks ranked so.
    model_wrench: bool = False

    def __post_init__(self) -> None:
        owner = type(self).__name__
        for name in ("hidden", "spread_hidden"):
            widths = getattr(self, name)
            require(isinstance(widths, tuple) and len(widths) > 0, owner,
                    f"{name} must be a non-empty tuple of widths, got {widths!r}")
            for width in widths:
                require_int(owner, f"{name} widths", width, lo=1)
        nonnegative = ("spread_scale", "segment_spacings", "segment_floor_margin", "segment_wall_margin",
                       "segment_shift_spread")
        require_finite_numbers(self, nonnegative + ("segment_up_cos",))
        for name in nonnegative:
            require(getattr(self, name) >= 0, owner, f"{name} must be >= 0, got {getattr(self, name)!r}")
        require(-1.0 <= self.segment_up_cos <= 1.0, owner,
                f"segment_up_cos must be in [-1, 1], got {self.segment_up_cos!r}")
        require_int(owner, "segment_min_points", self.segment_min_points, lo=1)
        require_int(owner, "spread_draws", self.spread_draws, lo=4)
        require(self.spread_draws % 4 == 0, owner, f"spread_draws must be a multiple of 4, got {self.spread_draws}")
        require_positive_numbers(self, ("cluster_radius", "segment_vote_gap", "segment_max_shift", "segment_cover_margin"))
        require_int(owner, "cluster_neighbours", self.cluster_neighbours, lo=1)
        require_int(owner, "voters", self.voters, lo=0)
        require_choice(owner, "wrench_definition", self.wrench_definition, VOTE_DEFINITIONS)
        require(isinstance(self.model_wrench, bool), owner, f"model_wrench must be true or false, got {self.model_wrench!r}")

    def to_dict(self) -> dict[str, Any]:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "CentreVoteConfig":
        return config_from_dict(cls, data)


class CentreVoteHead(nn.Module):
    """Per-point MLPs: (encoder features, normal) -> offset from the point to its parcel's centre, in metres
    (``mlp``), and the log of that vote's horizontal error, per axis (``spread``).

    The inputs are standardised with the training set's statistics (buffers, stored in the checkpoint); the
    outputs are learnt in ``LEVER_UNIT`` (decimetres), O(1) like the levers the decoder reads."""

    input_mean: torch.Tensor
    input_std: torch.Tensor

    def __init__(self, in_features: int, config: CentreVoteConfig = CentreVoteConfig()) -> None:
        super().__init__()
        require_int(type(self).__name__, "in_features", in_features, lo=1)
        self.config = config
        self.in_features = int(in_features)
        width = self.in_features + 3
        self.mlp = _mlp(width, config.hidden, 3)
        self.spread = _mlp(width, config.spread_hidden, 1)  # made second: the offsets' initial weights are as before
        self.register_buffer("input_mean", torch.zeros(self.in_features + 3))
        self.register_buffer("input_std", torch.ones(self.in_features + 3))

    def set_standardisation(self, inputs: torch.Tensor) -> None:
        """Standardise with the mean and spread of ``inputs`` (M, in_features + 3), as ``inputs_of`` makes them."""
        self.input_mean.copy_(inputs.mean(0))
        self.input_std.copy_(inputs.std(0) + 1e-3)

    def forward_units(self, inputs: torch.Tensor) -> torch.Tensor:
        """Offsets in ``LEVER_UNIT`` from prepared ``inputs`` (..., in_features + 3): what the training loss reads."""
        return self.mlp((inputs - self.input_mean) / self.input_std)

    def log_spread_units(self, inputs: torch.Tensor) -> torch.Tensor:
        """(...,) log of each vote's error per horizontal axis, in ``LEVER_UNIT``, from prepared ``inputs``."""
        return self.spread((inputs - self.input_mean) / self.input_std).squeeze(-1)

    def forward(self, features: torch.Tensor, normals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., 3) offsets and (...,) their predicted errors per horizontal axis, both in metres, for per-point
        ``features`` (..., F) and unit ``normals`` (..., 3)."""
        inputs = inputs_of(features, normals, self.in_features)
        return self.forward_units(inputs) * LEVER_UNIT, torch.exp(self.log_spread_units(inputs)) * LEVER_UNIT


def _mlp(width: int, hidden: tuple[int, ...], out: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for size in hidden:
        layers += [nn.Linear(width, size), nn.GELU()]
        width = size
    return nn.Sequential(*layers, nn.Linear(width, out))


def inputs_of(features: torch.Tensor, normals: torch.Tensor, in_features: int) -> torch.Tensor:
    """The head's input rows: the features, then the normal."""
    if features.shape[-1] != in_features or normals.shape[-1] != 3 or features.shape[:-1] != normals.shape[:-1]:
        raise ValueError(f"centre vote head needs features (..., {in_features}) and normals (..., 3) on the same "
                         f"points, got {tuple(features.shape)} and {tuple(normals.shape)}")
    return torch.cat([features.float(), normals.float()], dim=-1)


def cluster_centres(centres: np.ndarray, radius: float, neighbours: int, workers: int = 1,
                    spreads: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64: each voted centre averaged with its ``neighbours`` nearest votes within ``radius`` (itself
    among them), weighted by 1 / ``spreads``^2 (each vote's predicted error; None: equal weights); and (N,) the
    typical error of the votes averaged (their weighted mean spread; zeros without ``spreads``). ``workers``: the
    k-NN query's threads (the same neighbours, faster for many votes).

    Votes for one parcel scatter around its centre; their local mean is steadier than any one of them. The cap
    bounds the cost where votes crowd (all pairs within 4 cm on a synthetic pile: 1 million)."""
    centres = np.asarray(centres, dtype=np.float64)
    if centres.ndim != 2 or centres.shape[1] != 3:
        raise ValueError(f"centres must be (N, 3), got {centres.shape}")
    if not radius > 0 or int(neighbours) != neighbours or neighbours < 1:
        raise ValueError(f"need radius > 0 and neighbours >= 1, got {radius}, {neighbours}")
    spread = np.zeros(len(centres)) if spreads is None else np.asarray(spreads, dtype=np.float64)
    if spread.shape != (len(centres),) or not np.all(spread >= 0):
        raise ValueError(f"spreads must be (N,) = ({len(centres)},) and >= 0, got {spread.shape}")
    if len(centres) == 0:
        return centres.copy(), spread.copy()
    k = min(int(neighbours), len(centres))
    distances, index = cKDTree(centres).query(centres, k=k, distance_upper_bound=radius, workers=workers)
    distances, index = distances.reshape(len(centres), k), index.reshape(len(centres), k)
    found = np.isfinite(distances)  # beyond the radius: inf distance, index N
    weights = 1.0 / np.maximum(spread, 1e-6) ** 2 if spreads is not None else np.ones(len(centres))
    weights = np.where(found, np.append(weights, 0.0)[index], 0.0)
    total = weights.sum(axis=1)
    averaged = (np.vstack([centres, np.zeros((1, 3))])[index] * weights[..., None]).sum(axis=1) / total[:, None]
    return averaged, (np.append(spread, 0.0)[index] * weights).sum(axis=1) / total


def spread_draws(count: int) -> np.ndarray:
    """(count, 2) fixed samples of a 2-D standard normal, ``count`` a multiple of 4: rings of equal mass, their
    radii scaled so the mean square is 2, each ring's four points a quarter turn apart (rings turned by the golden
    angle). So the mean is 0 and each axis's variance 1, exactly, and the expected wrench is deterministic."""
    require_int("spread_draws", "count", count, lo=4)
    require(count % 4 == 0, "spread_draws", f"count must be a multiple of 4, got {count}")
    rings = count // 4
    radius = np.sqrt(-2.0 * np.log(1.0 - (np.arange(rings) + 0.5) / rings))
    radius *= np.sqrt(2.0 / np.mean(radius**2))
    angle = np.arange(rings)[:, None] * np.pi * (3.0 - np.sqrt(5.0)) + np.arange(4)[None, :] * (np.pi / 2)
    return np.stack([radius[:, None] * np.cos(angle), radius[:, None] * np.sin(angle)], axis=-1).reshape(count, 2)


def vote_wrench(points: np.ndarray, normals: np.ndarray, centres: np.ndarray, definition: str,
                spread: np.ndarray | None = None, draws: int = 16) -> np.ndarray:
    """(N,) float32: ``definition``'s wrench score of each contact about its voted centre (the shared formula);
    with ``spread`` (N,) metres per horizontal axis, the score expected over that error of the centre
    (``draws`` samples)."""
    require_choice("vote_wrench", "definition", definition, VOTE_DEFINITIONS)
    args = (np.asarray(points, dtype=np.float64), np.asarray(normals, dtype=np.float64),
            np.asarray(centres, dtype=np.float64))
    if spread is None:
        return wrench_scores(*args, definition_config(definition))
    return expected_wrench_scores(*args, spread, spread_draws(draws), definition_config(definition))


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
