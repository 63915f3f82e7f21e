"""Train Diffusion-Suction.

    python -m policies.diffusion.train --data DIR --out runs/diffusion --preset cpu --steps 5000 --batch-size 4

Resumable (``--resume`` continues from OUT/last.pt with the same data order and noise), deterministic under --seed.
``--init CHECKPOINT`` warm-starts from a trained model's weights: a fresh optimizer and learning-rate schedule over
``--steps``, and the start model's validation is the bar that ``best.pt`` must beat. The start checkpoint's own
record (step, provenance, SHA-256) is kept in every checkpoint the run writes, so the chain stays reproducible.
``--max-minutes`` bounds this invocation's wall time: past it, the run validates, writes its checkpoints at the step
it reached and stops (the log and the checkpoint record that step; the learning-rate schedule stays the one over
``--steps``), so a run on a lent machine of limited time always leaves a model behind.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler, Subset, default_collate

from parcelpick_env.cli import (
    UsageError,
    check_input_dir,
    check_input_file,
    check_output_path,
    run_cli,
)
from parcelpick_env.suction.label_sets import LABEL_SETS
from policies.diffusion.checkpoint import load_checkpoint, load_model, save_checkpoint
from policies.diffusion.config import TIMESTEP_SPACINGS, DiffusionConfig
from policies.diffusion.metrics import topk_precision
from policies.provenance import chain_parts, command_line, training_provenance
from policies.diffusion.model import DiffusionSuction, build_model
from policies.diffusion.neighbourhood import NeighbourhoodTransform

PRESETS = {"paper": DiffusionConfig, "cpu": DiffusionConfig.cpu, "tiny": DiffusionConfig.tiny}


class EpochBatches(Sampler[list[int]]):
    """Batches ``start..stop`` of epoch ``epoch``'s permutation, drawn from (seed, epoch): resuming replays the order."""

    def __init__(self, n: int, batch_size: int, seed: int, epoch: int, start: int, stop: int):
        self.perm = np.random.default_rng([seed, epoch]).permutation(n)
        self.bs, self.start, self.stop = batch_size, start, stop

    def __iter__(self) -> Iterator[list[int]]:
        for i in range(self.start, self.stop):
            yield self.perm[i * self.bs:(i + 1) * self.bs].tolist()

    def __len__(self) -> int:
        return self.stop - self.start


def _set_epoch(dataset: Dataset, epoch: int) -> None:
    """Vary the dataset's augmentation per epoch (ParcelSuctionDataset draws it from (seed, epoch, index))."""
    base = dataset.dataset if isinstance(dataset, Subset) else dataset
    if hasattr(base, "set_epoch"):
        base.set_epoch(epoch)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", type=Path, help="dataset root for dataset.torch_dataset.ParcelSuctionDataset")
    src.add_argument("--synthetic", type=int, metavar="SCENES", help="train on N synthetic box scenes (smoke test)")
    p.add_argument("--val-data", type=Path, help="validation root (default: hold out --val-fraction of --data)")
    p.add_argument("--label-set", choices=list(LABEL_SETS), default=None,
                   help="which stored label set to learn (docs/labels.md; default: the dataset's main one)")
    p.add_argument("--val-fraction", type=float, default=0.05)
    p.add_argument("--val-scenes", type=int, default=16, help="scenes used per validation")
    p.add_argument("--out", type=Path, default=Path("runs/diffusion"))
    p.add_argument("--preset", choices=sorted(PRESETS), default="cpu")
    p.add_argument("--num-points", type=int)
    p.add_argument("--encoder", choices=["pointnet2", "pointnet"])
    p.add_argument("--width", type=float)
    p.add_argument("--no-normals", action="store_true")
    p.add_argument("--no-visibility", action="store_true")
    levers = p.add_mutually_exclusive_group()  # the cpu preset conditions on them, the paper's does not
    levers.add_argument("--no-segment-levers", action="store_true",
                        help="do not condition on surface-segment lever arms")
    levers.add_argument("--segment-levers", action="store_true",
                        help="condition on surface-segment lever arms (e.g. the paper preset, whose GPU-trained model "
                             "picked further from the centre of mass; README)")
    p.add_argument("--segment-size", action="store_true",
                   help="also condition the decoder on each point's surface-segment size (radius of gyration)")
    p.add_argument("--levers-in-encoder", action="store_true",
                   help="feed the segment lever arms (and size) to the encoder beside the normals")
    p.add_argument("--diffusion-steps", type=int, help="training diffusion steps T (default 1000)")
    p.add_argument("--inference-steps", type=int, help="DDIM steps (default: 20 in the paper preset, 5 in cpu)")
    p.add_argument("--schedule", choices=["linear", "cosine"])
    p.add_argument("--prediction", choices=["eps", "x0"])
    p.add_argument("--timestep-spacing", choices=list(TIMESTEP_SPACINGS),
                   help="DDIM timesteps (default 'leading', see DiffusionConfig)")
    p.add_argument("--eta", type=float, help="DDIM noise, 0 (default, deterministic) to 1")
    p.add_argument("--map-loss-weight", type=float)
    p.add_argument("--positive-weight", type=float, help="loss weight 1 + w * label per point and channel")
    p.add_argument("--epochs", type=int, default=1)
    p.add_argument("--steps", type=int, help="optimisation steps (overrides --epochs)")
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--weight-decay", type=float, default=1e-4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--workers", type=int, default=0, help="DataLoader workers (neighbourhoods are computed there)")
    p.add_argument("--val-every", type=int, default=200)
    p.add_argument("--max-minutes", type=float, default=None,
                   help="stop after this many minutes of this invocation, validated and saved at the step reached")
    start = p.add_mutually_exclusive_group()
    start.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    start.add_argument("--init", type=Path, metavar="CHECKPOINT",
                       help="warm-start from this checkpoint's weights (its config must match the flags); a fresh "
                            "optimizer and schedule, and best.pt only where validation beats the start model's")
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def make_config(args: argparse.Namespace) -> DiffusionConfig:
    overrides = {k: v for k, v in {
        "num_points": args.num_points, "encoder": args.encoder, "width": args.width,
        "train_steps": args.diffusion_steps, "inference_steps": args.inference_steps, "schedule": args.schedule,
        "prediction": args.prediction, "timestep_spacing": args.timestep_spacing, "eta": args.eta,
        "map_loss_weight": args.map_loss_weight,
        "positive_weight": args.positive_weight}.items() if v is not None}
    if args.no_normals:
        overrides["use_normals"] = False
    if args.no_visibility:
        overrides["use_visibility"] = False
    if args.no_segment_levers or args.segment_levers:
        overrides["segment_levers"] = bool(args.segment_levers)
    if args.segment_size:
        overrides["segment_size"] = True
    if args.levers_in_encoder:
        overrides["levers_in_encoder"] = True
    if args.preset == "paper":
        return DiffusionConfig(**overrides)
    return PRESETS[args.preset](**overrides)


def make_datasets(args: argparse.Namespace, config: DiffusionConfig) -> tuple[Dataset, Dataset]:
    transform = NeighbourhoodTransform(config)
    if args.synthetic is not None:
        from policies.diffusion.synthetic import SyntheticSuctionDataset

        n_val = max(1, args.synthetic // 10)
        return (SyntheticSuctionDataset(args.synthetic, config.num_points, args.seed, transform),
                SyntheticSuctionDataset(n_val, config.num_points, args.seed + 1, transform))
    try:
        from dataset.torch_dataset import ParcelSuctionDataset
    except ImportError as e:
        raise SystemExit(f"error: dataset.torch_dataset.ParcelSuctionDataset is not importable ({e})") from e
    if not args.data.exists():
        raise SystemExit(f"error: --data {args.data} does not exist")
    try:
        train = ParcelSuctionDataset(args.data, num_points=config.num_points, augment=True, transform=transform,
                                     seed=args.seed, label_set=args.label_set)
        val = None if args.val_data is None else ParcelSuctionDataset(
            args.val_data, num_points=config.num_points, augment=False, transform=transform, seed=args.seed,
            label_set=args.label_set)
    except ValueError as e:  # a label set the dataset does not hold
        raise SystemExit(f"error: {e}") from e
    for flag, root, data in (("--data", args.data, train), ("--val-data", args.val_data, val)):
        stored = None if data is None else data.store.config.get("annotation_points")
        if stored is not None and config.num_points > int(stored):
            raise SystemExit(f"error: {flag} {root} stores {stored} points per scene, fewer than the model's "
                             f"{config.num_points} (--num-points / --preset): each point would be fed twice; "
                             f"generate it with `python -m dataset.generate --points {config.num_points}`")
    if val is not None:
        return train, val
    n = len(train)
    if n < 2:
        raise SystemExit(f"error: {args.data} holds {n} scene(s); need >= 2 to hold one out for validation")
    perm = np.random.default_rng(args.seed).permutation(n)
    n_val = min(n - 1, max(1, int(round(n * args.val_fraction))))
    val_base = ParcelSuctionDataset(args.data, num_points=config.num_points, augment=False, transform=transform,
                                    seed=args.seed, label_set=args.label_set)
    return Subset(train, perm[n_val:].tolist()), Subset(val_base, perm[:n_val].tolist())


def to_device(batch: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items() if isinstance(v, torch.Tensor)}


@torch.no_grad()
def validate(model: DiffusionSuction, loader: DataLoader, device: torch.device, seed: int,
             max_scenes: int) -> dict[str, float]:
    """Mean training loss at fixed noise, and the top-k precision AP proxy of the sampled scores."""
    model.eval()
    g = torch.Generator(device=device).manual_seed(seed)
    losses, aps, seen = [], [], 0
    for batch in loader:
        if seen >= max_scenes:
            break
        batch = to_device(batch, device)
        losses.append(float(model.forward_train(batch, g)["loss"]))
        scores = model.sample(model.encode(batch), generator=g)
        aps.append(topk_precision(scores.prod(-1), batch["labels"].prod(-1)))
        seen += batch["points"].shape[0]
    model.train()
    return {"val_loss": float(np.mean(losses)), "val_ap_proxy": float(np.mean(aps))}


def lr_at(step: int, total: int, base: float) -> float:
    """Linear warm-up over 2% of the steps, then cosine decay to 5% of the base rate."""
    warm = max(1, total // 50)
    if step < warm:
        return base * (step + 1) / warm
    frac = (step - warm) / max(1, total - warm)
    return base * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * frac)))


def train(args: argparse.Namespace) -> dict[str, float]:
    started = time.perf_counter()  # this invocation's wall time (chain_parts adds a resumed run's earlier parts)
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda but CUDA is not available")
    config = make_config(args)
    args.out.mkdir(parents=True, exist_ok=True)
    model = build_model(config, seed=args.seed).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    start, best = 0, -1.0
    last = args.out / "last.pt"
    init: dict[str, Any] | None = None  # the warm start's record, kept in every checkpoint of the run
    earlier: dict[str, Any] | None = None  # a resumed run's provenance so far (chain_parts)
    if args.resume:
        payload = load_checkpoint(last, map_location=device)
        if payload["config"] != config:
            raise SystemExit(f"error: {last} was trained with a different config; drop --resume or match the flags")
        model.load_state_dict(payload["model"])
        optimizer.load_state_dict(payload["optimizer"])
        start, best = payload["step"], payload["extra"].get("best_ap_proxy", -1.0)
        init = payload["extra"].get("init")
        earlier = payload["extra"].get("provenance")
    elif args.init is not None:
        init = warm_start(model, args.init, config, device)
    train_set, val_set = make_datasets(args, config)
    bs = min(args.batch_size, len(train_set))
    per_epoch = max(1, len(train_set) // bs)
    total = args.steps if args.steps is not None else args.epochs * per_epoch
    val_loader = DataLoader(val_set, batch_size=bs, shuffle=False, num_workers=args.workers)
    (args.out / "config.json").write_text(json.dumps(config.to_dict(), indent=1))
    log = (args.out / "log.jsonl").open("a")
    from tqdm import tqdm

    bar = tqdm(total=total, initial=start, disable=args.no_progress, desc="train", file=sys.stderr)
    metrics: dict[str, float] = {}
    improved = False  # whether this invocation wrote best.pt
    model.train()
    t0 = time.perf_counter()
    deadline = None if args.max_minutes is None else started + 60.0 * args.max_minutes
    out_of_time = False
    step = start
    if start == 0 and total > 0:  # the untrained (or warm-start) baseline, so the log shows what training bought
        base = {"step": 0, **validate(model, val_loader, device, args.seed, args.val_scenes)}
        log.write(json.dumps(base) + "\n")
        bar.write(json.dumps(base))
        if init is not None:  # a warm start is kept only where it improves on where it started
            best = base["val_ap_proxy"]
    while step < total:
        epoch, offset = divmod(step, per_epoch)
        _set_epoch(train_set, epoch)
        sampler = EpochBatches(len(train_set), bs, args.seed, epoch, offset, min(per_epoch, offset + total - step))
        loader = DataLoader(train_set, batch_sampler=sampler, num_workers=args.workers, collate_fn=default_collate,
                            pin_memory=device.type == "cuda")
        for batch in loader:
            for group in optimizer.param_groups:
                group["lr"] = lr_at(step, total, args.lr)
            g = torch.Generator(device=device).manual_seed(args.seed * 1_000_003 + step)  # noise fixed by (seed, step)
            losses = model.forward_train(to_device(batch, device), g)
            optimizer.zero_grad(set_to_none=True)
            losses["loss"].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            optimizer.step()
            step += 1
            bar.update(1)
            bar.set_postfix({k: f"{float(v.detach()):.4f}" for k, v in losses.items()})
            out_of_time = deadline is not None and time.perf_counter() > deadline and step < total
            if step % args.val_every == 0 or step == total or out_of_time:
                metrics = {"step": step, "loss": float(losses["loss"].detach()),
                           "sec_per_step": (time.perf_counter() - t0) / max(1, step - start),
                           **validate(model, val_loader, device, args.seed, args.val_scenes)}
                is_best = metrics["val_ap_proxy"] > best
                best = max(best, metrics["val_ap_proxy"])
                extra = {"best_ap_proxy": best, "metrics": metrics,
                         "provenance": chain_parts(training_provenance(getattr(args, "command", "not recorded"),
                                                                       args.seed, args.data, started), earlier)}
                if init is not None:
                    extra["init"] = init
                save_checkpoint(last, model, optimizer, step, extra)
                if is_best:
                    save_checkpoint(args.out / "best.pt", model, None, step, extra)
                    improved = True
                log.write(json.dumps(metrics) + "\n")
                log.flush()
                bar.write(json.dumps(metrics))
            if out_of_time:
                break
        if out_of_time:
            stopped = {"stopped_at_step": step, "of_steps": total, "max_minutes": args.max_minutes}
            log.write(json.dumps(stopped) + "\n")
            bar.write(f"--max-minutes {args.max_minutes} reached: stopped at step {step} of {total}")
            break
    bar.close()
    log.close()
    if init is not None and start == 0 and not improved:
        print(f"no validation improved on --init's ({best:.4f}): {args.out / 'best.pt'} was not written",
              file=sys.stderr)
    return metrics


def warm_start(model: DiffusionSuction, path: Path, config: DiffusionConfig, device: torch.device) -> dict[str, Any]:
    """Load ``path``'s weights into ``model`` (same config, else SystemExit naming the fields) and return its record:
    file, SHA-256, step and the provenance of the run that made it."""
    try:
        start, payload = load_model(path, map_location=device, expected=config)
    except (FileNotFoundError, ValueError) as e:
        raise SystemExit(f"error: --init {e}; match the flags to the checkpoint") from e
    model.load_state_dict(start.state_dict())
    extra = payload.get("extra", {})
    return {"checkpoint": str(path), "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
            "step": int(payload.get("step", 0)), "provenance": extra.get("provenance", "not recorded"),
            "init": extra.get("init")}  # a chain of warm starts stays whole


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    args.command = command_line("policies.diffusion.train", argv)  # recorded in every checkpoint's provenance
    for flag, path in (("--data", args.data), ("--val-data", args.val_data)):
        if path is not None:
            check_input_dir(path, flag)
    check_output_path(args.out, "--out", directory=True)
    if args.resume:
        check_input_file(args.out / "last.pt", "--resume")
    if args.init is not None:
        check_input_file(args.init, "--init")
    if args.max_minutes is not None and not (math.isfinite(args.max_minutes) and args.max_minutes > 0):
        raise UsageError(f"--max-minutes must be a positive number, got {args.max_minutes}")
    train(args)


if __name__ == "__main__":
    sys.exit(run_cli(main))
