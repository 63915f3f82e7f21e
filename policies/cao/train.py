"""Train the Cao et al. heatmap network on a generated dataset.

    python -m policies.cao.train --data data/train --out policies/cao/checkpoint.pt --epochs 30 --seed 0

Every scene is turned into (input, target) tensors once, up front: at the default 160x120 input a
scene is ~0.5 MB, so a few hundred scenes fit in memory and each epoch is pure convolution.
The checkpoint keeps the config (so the policy rebuilds the exact network and pre-processing), the
weights with the best validation loss, and a small record of how it was trained.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from dataset.suctionnet.views import open_store
from parcelpick_env.cli import check_input_dir, check_output_path, run_cli
from policies.cao.config import CaoConfig
from policies.cao.network import CaoNet, prepare_input
from policies.cao.targets import frame_from_record, frame_targets
from policies.checkpoint_io import save_atomic
from policies.provenance import command_line, training_provenance


def load_tensors(data_dir: str | os.PathLike, config: CaoConfig, max_scenes: int | None = None,
                 progress: bool = True) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """(S, C, h, w) inputs (``config.input_channels``) and (S, 2, h, w) [seal, centre] targets for every stored scene."""
    store = open_store(data_dir)  # a dataset directory or a SuctionNet root
    count = len(store) if max_scenes is None else min(len(store), max_scenes)
    if count == 0:
        raise ValueError(f"dataset {data_dir} holds no scenes")
    inputs = np.empty((count, config.input_channels, config.input_height, config.input_width), dtype=np.float32)
    targets = np.empty((count, 2, config.input_height, config.input_width), dtype=np.float32)
    for i in tqdm(range(count), desc="targets", unit="scene", disable=not progress):
        frame = frame_from_record(store.scene(i))
        inputs[i] = prepare_input(frame.rgb, frame.depth, config)
        targets[i] = frame_targets(frame, config)
    info = {"scenes": count, "dataset_config": dict(store.config)}
    store.close()
    return torch.from_numpy(inputs), torch.from_numpy(targets), info


def _random_flips(x: torch.Tensor, y: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Flip each sample left-right and/or up-down; heatmaps are image-space, so targets flip with inputs."""
    flips = torch.rand(len(x), 2, generator=generator) < 0.5
    for dim, column in ((-1, 0), (-2, 1)):
        pick = flips[:, column]
        if pick.any():
            x, y = x.clone(), y.clone()
            x[pick] = x[pick].flip(dim)
            y[pick] = y[pick].flip(dim)
    return x, y


def heatmap_loss(logits: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy against the soft [seal, centre] targets, averaged over both maps."""
    return F.binary_cross_entropy_with_logits(logits, targets)


def _evaluate(net: CaoNet, x: torch.Tensor, y: torch.Tensor, batch_size: int) -> float:
    net.eval()
    total = 0.0
    with torch.inference_mode():
        for start in range(0, len(x), batch_size):
            xb, yb = x[start:start + batch_size], y[start:start + batch_size]
            total += float(heatmap_loss(net(xb), yb)) * len(xb)
    return total / len(x)


def train(data_dir: str | os.PathLike, out: str | os.PathLike, config: CaoConfig | None = None, seed: int = 0,
          max_scenes: int | None = None, threads: int | None = None, progress: bool = True,
          command: str | None = None) -> dict[str, Any]:
    """Fit the network and write the checkpoint; returns the per-epoch history and timings.

    ``command`` is the command line stored in the checkpoint's provenance (None: 'not recorded').

    ``threads`` sets torch's CPU threads for the run (restored afterwards); None keeps torch's setting.
    """
    config = config or CaoConfig()
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    if threads is not None and threads < 1:
        raise ValueError(f"threads must be >= 1 or None, got {threads}")
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return _train(data_dir, out, config, seed, max_scenes, progress, command)
    finally:
        torch.set_num_threads(previous)


def _train(data_dir: str | os.PathLike, out: str | os.PathLike, config: CaoConfig, seed: int,
           max_scenes: int | None, progress: bool, command: str | None = None) -> dict[str, Any]:
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    start = time.perf_counter()
    x, y, data_info = load_tensors(data_dir, config, max_scenes=max_scenes, progress=progress)
    prep_seconds = time.perf_counter() - start

    order = torch.randperm(len(x), generator=generator)
    n_val = int(round(config.val_fraction * len(x))) if len(x) > 1 else 0
    n_val = min(max(n_val, 1 if config.val_fraction > 0 and len(x) > 1 else 0), len(x) - 1)
    val_idx, train_idx = order[:n_val], order[n_val:]
    x_train, y_train, x_val, y_val = x[train_idx], y[train_idx], x[val_idx], y[val_idx]

    net = CaoNet(config)
    optimiser = torch.optim.AdamW(net.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay)
    steps_per_epoch = -(-len(x_train) // config.batch_size)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, max_lr=config.learning_rate,
                                                   total_steps=config.epochs * steps_per_epoch)
    history: list[dict[str, float]] = []
    best_loss, best_state = float("inf"), None
    bar = tqdm(range(config.epochs), desc="epochs", unit="epoch", disable=not progress)
    train_start = time.perf_counter()
    for epoch in bar:
        net.train()
        perm = torch.randperm(len(x_train), generator=generator)
        running = 0.0
        for step in range(steps_per_epoch):
            batch = perm[step * config.batch_size:(step + 1) * config.batch_size]
            xb, yb = x_train[batch], y_train[batch]
            if config.augment_flips:
                xb, yb = _random_flips(xb, yb, generator)
            loss = heatmap_loss(net(xb), yb)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            schedule.step()
            running += float(loss.detach()) * len(batch)
        train_loss = running / len(x_train)
        val_loss = _evaluate(net, x_val, y_val, config.batch_size) if len(x_val) else float("nan")
        history.append({"epoch": epoch + 1, "train_loss": train_loss, "val_loss": val_loss})
        bar.set_postfix(train=f"{train_loss:.4f}", val=f"{val_loss:.4f}")
        monitored = val_loss if len(x_val) else train_loss
        if monitored < best_loss:
            best_loss = monitored
            best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
    train_seconds = time.perf_counter() - train_start
    if best_state is None:  # every epoch's loss was NaN: keep the weights, the history shows why
        best_state = net.state_dict()

    meta = {
        "seed": seed, "data": str(data_dir), "scenes": data_info["scenes"], "train_scenes": len(x_train),
        "val_scenes": len(x_val), "best_loss": best_loss, "history": history,
        "prep_seconds": prep_seconds, "train_seconds": train_seconds, "threads": torch.get_num_threads(),
        "dataset_config": {k: v for k, v in data_info["dataset_config"].items()
                           if isinstance(v, (int, float, str, bool))},
    }
    meta["provenance"] = training_provenance(command or "not recorded", seed, data_dir, start)
    save_atomic({"config": config.to_dict(), "state_dict": best_state, "meta": meta}, out)
    return meta


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="dataset directory made by `python -m dataset.generate`")
    parser.add_argument("--out", required=True, help="checkpoint path to write")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-scenes", type=int, default=None, help="use only the first N scenes")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    defaults = CaoConfig()
    for field in ("epochs", "batch_size", "learning_rate", "input_height", "input_width", "val_fraction"):
        kind = type(getattr(defaults, field))
        parser.add_argument(f"--{field.replace('_', '-')}", type=kind, default=getattr(defaults, field))
    parser.add_argument("--widths", type=int, nargs="+", default=list(defaults.widths))
    parser.add_argument("--no-colour", action="store_true",
                        help="read the depth (relief) plane alone: the ablation of what colour gives the baseline")
    args = parser.parse_args(argv)
    try:
        check_input_dir(args.data, "--data")
        check_output_path(args.out, "--out")
        config = dataclasses.replace(
            defaults, epochs=args.epochs, batch_size=args.batch_size, learning_rate=args.learning_rate,
            input_height=args.input_height, input_width=args.input_width, val_fraction=args.val_fraction,
            widths=tuple(args.widths), colour=not args.no_colour)
        meta = train(args.data, args.out, config, seed=args.seed, max_scenes=args.max_scenes, threads=args.threads,
                     progress=not args.quiet, command=command_line("policies.cao.train", argv))
    except (ValueError, FileNotFoundError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    first, last = meta["history"][0], meta["history"][-1]
    print(f"trained on {meta['train_scenes']} scenes ({meta['val_scenes']} val) in {meta['train_seconds']:.1f} s: "
          f"train loss {first['train_loss']:.4f} -> {last['train_loss']:.4f}, best {meta['best_loss']:.4f}; "
          f"wrote {args.out} ({Path(args.out).stat().st_size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
