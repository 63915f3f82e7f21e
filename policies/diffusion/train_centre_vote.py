"""Train the centre vote head (``centre_vote.py``) on a Diffusion-Suction checkpoint's frozen features.

    python -m policies.diffusion.train_centre_vote --data data/train_sn [data/more ...] \
        --out policies/diffusion/checkpoints/centre_vote.pt

Per stored scene: the checkpoint's encoder features at the stored cloud (as the policy computes them), and for
every point on a parcel (the stored ``object_ids``) the offset to that parcel's surface centroid, from the true
meshes (``dataset.scene_record``). Then the head learns offsets with a smooth L1 loss on random batches of points,
and after them the error of its own votes: a Gaussian likelihood of the horizontal residuals (``fit_spread``).
The head records the checkpoint's SHA-256, so it is never paired with another model's features.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import nn

from dataset.scene_record import require_keys, scene_from_record
from dataset.storage import open_dataset
from parcelpick_env.cli import UsageError, check_input_dir, check_input_file, check_output_path, run_cli
from parcelpick_env.config_checks import require, require_positive_ints, require_positive_numbers
from parcelpick_env.suction.geometry import surface_centroid
from policies.diffusion.centre_vote import (CentreVoteConfig, CentreVoteHead, file_sha256, inputs_of,
                                            save_centre_vote)
from policies.diffusion.checkpoint import DEFAULT_CHECKPOINT
from policies.diffusion.policy import DiffusionSuctionPolicy
from policies.provenance import command_line, manifest_sha256, training_provenance
from policies.surface_segments import LEVER_UNIT


@dataclass(frozen=True)
class CentreVoteTraining:
    """The head's optimisation (the shipped head's values)."""

    steps: int = 3000
    batch_points: int = 4096  # points per step, drawn from every scene's parcel points
    lr: float = 1e-3  # AdamW, cosine to 0
    weight_decay: float = 1e-4
    beta: float = 0.1  # smooth L1's switch from quadratic to linear, in LEVER_UNIT (1 cm)
    spread_steps: int = 3000  # then the votes' error, with the offsets frozen (same batches, lr and schedule)

    def __post_init__(self) -> None:
        require_positive_ints(self, ("steps", "batch_points", "spread_steps"))
        require_positive_numbers(self, ("lr", "beta"))
        require(self.weight_decay >= 0, type(self).__name__, f"weight_decay must be >= 0, got {self.weight_decay!r}")


def vote_targets(record: dict, points: np.ndarray, object_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) offsets from each point to its parcel's surface centroid (the centre SuctionNet's wrench is about),
    and the (N,) mask of points on a parcel."""
    centroids = np.array([surface_centroid(mesh) for mesh in scene_from_record(record).world_meshes()]).reshape(-1, 3)
    on_parcel = (object_ids >= 0) & (object_ids < len(centroids))
    offsets = np.zeros_like(points, dtype=np.float64)
    offsets[on_parcel] = centroids[object_ids[on_parcel]] - points[on_parcel]
    return offsets, on_parcel


def collect(data: Path, policy: DiffusionSuctionPolicy, scenes: int | None, progress: bool
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Head inputs (M, F + 3) and offset targets (M, 3, in LEVER_UNIT) of every parcel point of the stored scenes."""
    from tqdm import tqdm

    store = open_dataset(data)
    inputs, targets = [], []
    try:
        total = len(store) if scenes is None else min(scenes, len(store))
        for i in tqdm(range(total), desc=f"features {data}", disable=not progress, file=sys.stderr):
            record = store.scene(i)
            require_keys(record, ("points", "normals", "object_ids"), f"{data}: scene {i}")
            points = np.asarray(record["points"], dtype=np.float32)
            normals = np.asarray(record["normals"], dtype=np.float32)
            offsets, on_parcel = vote_targets(record, points, np.asarray(record["object_ids"], dtype=np.int64))
            features = policy.encode_cloud(points, normals)[0]
            inputs.append(inputs_of(features, torch.from_numpy(normals), policy.model.encode_width)[on_parcel])
            targets.append(torch.from_numpy(offsets[on_parcel] / LEVER_UNIT).float())
    finally:
        store.close()
    return torch.cat(inputs), torch.cat(targets)


def fit(head: CentreVoteHead, inputs: torch.Tensor, targets: torch.Tensor, training: CentreVoteTraining, seed: int,
        progress: bool = False) -> list[float]:
    """Train ``head``'s offsets in place; the loss every 100 steps."""
    if len(inputs) == 0:
        raise ValueError("no parcel points to learn centre votes from")
    head.set_standardisation(inputs)

    def loss(batch: torch.Tensor) -> torch.Tensor:
        return nn.functional.smooth_l1_loss(head.forward_units(inputs[batch]), targets[batch], beta=training.beta)
    return _optimise(head.mlp, loss, len(inputs), training.steps, training, seed, "centre votes", progress)


def fit_spread(head: CentreVoteHead, inputs: torch.Tensor, targets: torch.Tensor, training: CentreVoteTraining,
               seed: int, progress: bool = False) -> list[float]:
    """Train ``head``'s spread in place, after ``fit``: the Gaussian negative log-likelihood of the fitted votes'
    horizontal residuals under each vote's predicted error; the loss every 100 steps."""
    if len(inputs) == 0:
        raise ValueError("no parcel points to learn the votes' spread from")
    with torch.inference_mode():
        chunks = [slice(i, i + 65536) for i in range(0, len(inputs), 65536)]
        residuals = torch.cat([head.forward_units(inputs[c]) - targets[c] for c in chunks])[:, :2].clone()

    def loss(batch: torch.Tensor) -> torch.Tensor:
        variance = torch.exp(2.0 * head.log_spread_units(inputs[batch]))[:, None].expand(-1, 2)
        return nn.functional.gaussian_nll_loss(torch.zeros_like(residuals[batch]), residuals[batch], variance)
    return _optimise(head.spread, loss, len(inputs), training.spread_steps, training, seed, "vote spread", progress)


def _optimise(module: nn.Module, loss_of: Callable[[torch.Tensor], torch.Tensor], rows: int, steps: int,
              training: CentreVoteTraining, seed: int, desc: str, progress: bool) -> list[float]:
    """AdamW with a cosine schedule on ``module``'s parameters, each step on ``batch_points`` random rows."""
    from tqdm import tqdm

    generator = torch.Generator().manual_seed(seed)
    module.train()
    optimiser = torch.optim.AdamW(module.parameters(), training.lr, weight_decay=training.weight_decay)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, steps)
    losses = []
    for step in tqdm(range(steps), desc=desc, disable=not progress, file=sys.stderr):
        loss = loss_of(torch.randint(rows, (training.batch_points,), generator=generator))
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
        if step % 100 == 0 or step == steps - 1:
            losses.append(float(loss.detach()))
    module.eval()
    return losses


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    defaults = CentreVoteTraining()
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, nargs="+", required=True,
                        help="one or more dataset directories (dataset.generate)")
    parser.add_argument("--checkpoint", type=Path, default=DEFAULT_CHECKPOINT,
                        help="the Diffusion-Suction checkpoint whose features the head reads (default: shipped)")
    parser.add_argument("--out", type=Path, default=Path("runs/centre_vote.pt"), help="where to write the head")
    parser.add_argument("--scenes", type=int, default=None, help="use the first N scenes of each (default: all)")
    parser.add_argument("--steps", type=int, default=defaults.steps)
    parser.add_argument("--batch-points", type=int, default=defaults.batch_points)
    parser.add_argument("--spread-steps", type=int, default=defaults.spread_steps)
    parser.add_argument("--lr", type=float, default=defaults.lr)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--no-progress", action="store_true")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    command = command_line("policies.diffusion.train_centre_vote", argv)
    started = time.perf_counter()
    for data in args.data:
        check_input_dir(data, "--data")
    check_input_file(args.checkpoint, "--checkpoint")
    check_output_path(args.out, "--out")
    if args.scenes is not None and args.scenes < 1:
        raise UsageError(f"--scenes must be >= 1, got {args.scenes}")
    if args.threads < 1 or args.seed < 0:
        raise UsageError(f"--threads must be >= 1 and --seed >= 0, got {args.threads}, {args.seed}")
    try:
        training = CentreVoteTraining(steps=args.steps, batch_points=args.batch_points, lr=args.lr,
                                      spread_steps=args.spread_steps)
    except ValueError as e:
        raise UsageError(str(e)) from e
    torch.set_num_threads(args.threads)
    policy = DiffusionSuctionPolicy(args.checkpoint, record_trajectory=False)
    parts = [collect(data, policy, args.scenes, not args.no_progress) for data in args.data]
    inputs, targets = torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
    torch.manual_seed(args.seed)  # the head's initial weights
    head = CentreVoteHead(policy.model.encode_width, CentreVoteConfig())
    losses = fit(head, inputs, targets, training, args.seed, not args.no_progress)
    spread_losses = fit_spread(head, inputs, targets, training, args.seed, not args.no_progress)
    provenance = training_provenance(command, args.seed, args.data[0], started)  # the first manifest; all below
    save_centre_vote(args.out, head, file_sha256(args.checkpoint),
                     {"provenance": provenance, "losses": losses, "spread_losses": spread_losses,
                      "points": int(len(inputs)),
                      "dataset_manifests_sha256": {str(d): manifest_sha256(d) for d in args.data},
                      "training": {k: getattr(training, k) for k in training.__dataclass_fields__}})
    print(f"wrote {args.out}: {len(inputs)} parcel points, final loss {losses[-1]:.4f} (spread "
          f"{spread_losses[-1]:.4f}), "
          f"{provenance['wall_time_s']:.0f} s")


if __name__ == "__main__":
    sys.exit(run_cli(main))
