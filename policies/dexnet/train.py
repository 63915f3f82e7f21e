"""Train the Dex-Net 3.0 style suction quality CNN on a ParcelPick dataset.

    python -m policies.dexnet.train --data data/train --out policies/dexnet/checkpoint.pt --epochs 10 --seed 0

A sample is an annotation point that the camera sees (its depth agrees with the depth image) and whose
approach is within the policy's angle of vertical. Its crop is cut from the scene's depth image at the
point's projection, exactly as the policy cuts crops at inference, and its target is the dataset's
analytic quality ``seal * wrench * collision`` (visibility is a per-object property the crop cannot
see, as in Dex-Net 3.0). Positives are rare, so each epoch draws a class-balanced sample, and the kept
weights are those of the epoch with the lowest class-balanced validation loss.

The shipped ``checkpoint.pt`` (0.74 MB) was trained on 200 scenes made by

    python -m dataset.generate --out data/cao_train --scenes 200 --split train --workers 1 --seed 0 \
        --width 160 --height 120 --points 1024 --scenes-per-shard 25

with ``python -m policies.dexnet.train --data data/cao_train --out policies/dexnet/checkpoint.pt
--epochs 10 --seed 0 --threads 1`` (the checkpoint's metadata holds the exact command and history).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from parcelpick_env.cli import check_input_dir, check_output_path, run_cli
from policies.observation import check_camera
from policies.provenance import NOT_RECORDED, command_line, training_provenance

from .config import DexNetConfig, TrainConfig
from .crops import DepthMosaic
from .network import SuctionQualityNet, save_checkpoint
from .projection import approach_angles, eligible_points

SCENE_KEYS = ("depth", "intrinsics", "extrinsics", "points", "normals", "labels")
TARGET_CHANNELS = (0, 1, 2)  # seal, wrench, collision in the dataset's label order


@dataclass
class SampleSet:
    """Every training sample of a set of scenes, plus the depth mosaic their crops come from."""

    mosaic: DepthMosaic
    image_index: np.ndarray  # (M,) int64
    uv: np.ndarray  # (M, 2) float32
    depth: np.ndarray  # (M,) float32, camera z of the point
    image_angle: np.ndarray  # (M,) float32
    tilt: np.ndarray  # (M,) float32
    fx: np.ndarray  # (M,) float32
    fy: np.ndarray  # (M,) float32
    target: np.ndarray  # (M,) float32 in [0, 1]

    def __len__(self) -> int:
        return int(self.target.shape[0])

    def batch(self, idx: np.ndarray, config: DexNetConfig) -> tuple[torch.Tensor, ...]:
        crops = self.mosaic.crops(self.uv[idx], self.depth[idx], self.image_angle[idx], self.fx[idx], self.fy[idx],
                                  config, image_index=self.image_index[idx])
        return (crops, torch.from_numpy(self.depth[idx]), torch.from_numpy(self.tilt[idx]),
                torch.from_numpy(self.target[idx]))


def scene_samples(record: Mapping[str, np.ndarray], config: TrainConfig,
                  rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The usable annotation points of one scene record, as per-sample arrays (without the image)."""
    missing = [k for k in SCENE_KEYS if k not in record]
    if missing:
        raise ValueError(f"scene record lacks {missing}; generate the dataset with images stored")
    depth = np.asarray(record["depth"], dtype=np.float32)
    depth = depth[..., 0] if depth.ndim == 3 and depth.shape[-1] == 1 else depth
    K, T = check_camera(record["intrinsics"], record["extrinsics"])
    points = np.asarray(record["points"], dtype=np.float64)
    normals = np.asarray(record["normals"], dtype=np.float64)
    labels = np.asarray(record["labels"], dtype=np.float64)
    if depth.ndim != 2 or points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape \
            or labels.ndim != 2 or labels.shape[0] != len(points) or labels.shape[1] < 3:
        raise ValueError(f"bad scene arrays: depth {depth.shape}, points {points.shape}, normals {normals.shape}, "
                         f"labels {labels.shape}")
    keep, uv, z, unit = eligible_points(depth, points, normals, K, T, config.dexnet.min_vertical_cos,
                                        config.dexnet.visibility_tolerance)
    finite = np.isfinite(labels[keep]).all(axis=1)
    keep, uv, z, unit = keep[finite], uv[finite], z[finite], unit[finite]
    if len(keep) > config.max_points_per_scene:
        pick = np.sort(rng.choice(len(keep), size=config.max_points_per_scene, replace=False))
        keep, uv, z, unit = keep[pick], uv[pick], z[pick], unit[pick]
    image_angle, tilt = approach_angles(unit, T)
    return {
        "uv": uv.astype(np.float32), "depth": z.astype(np.float32),
        "image_angle": image_angle.astype(np.float32), "tilt": tilt.astype(np.float32),
        "fx": np.full(len(keep), K[0, 0], np.float32), "fy": np.full(len(keep), K[1, 1], np.float32),
        "target": np.clip(np.prod(labels[keep][:, TARGET_CHANNELS], axis=1), 0, 1).astype(np.float32),
        "image": depth,
    }


def build_samples(records: Iterable[Mapping[str, np.ndarray]], config: TrainConfig,
                  rng: np.random.Generator) -> SampleSet:
    """One SampleSet over scene records that share an image size."""
    parts = [scene_samples(r, config, rng) for r in records]
    if not parts:
        raise ValueError("no scenes to build samples from")
    shapes = {p["image"].shape for p in parts}
    if len(shapes) != 1:
        raise ValueError(f"all scenes must share one image size, got {sorted(shapes)}")
    image_index = np.concatenate([np.full(len(p["target"]), i, np.int64) for i, p in enumerate(parts)])
    cat = {k: np.concatenate([p[k] for p in parts]) for k in ("uv", "depth", "image_angle", "tilt", "fx", "fy",
                                                                 "target")}
    return SampleSet(mosaic=DepthMosaic(np.stack([p["image"] for p in parts])), image_index=image_index, **cat)


def load_records(data_dir: str | Path) -> list[dict[str, np.ndarray]]:
    """The arrays training needs from every scene of a dataset directory made by ``dataset.generate``."""
    from dataset.suctionnet.views import open_store

    dataset = open_store(data_dir)  # a dataset directory or a SuctionNet root
    try:
        return [dataset.scene(i, keys=SCENE_KEYS) for i in range(len(dataset))]
    finally:
        dataset.close()


def balanced_indices(target: np.ndarray, threshold: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` sample indices, half positives (target >= threshold) and half negatives, with replacement."""
    positive = np.flatnonzero(target >= threshold)
    negative = np.flatnonzero(target < threshold)
    if len(positive) == 0 or len(negative) == 0:
        return rng.integers(0, len(target), size=n)
    half = n // 2
    return rng.permutation(np.concatenate([rng.choice(positive, size=half), rng.choice(negative, size=n - half)]))


@torch.no_grad()
def evaluate(model: SuctionQualityNet, samples: SampleSet, idx: np.ndarray, config: TrainConfig) -> dict[str, float]:
    """BCE over ``idx``: plain, and class-balanced (mean of the positive and negative means, the quantity
    balanced sampling trains on, so model selection is not fooled by the rarity of positives); plus the
    balanced accuracy at the positive threshold."""
    model.eval()
    losses, probs, targets = [], [], []
    for start in range(0, len(idx), 512):
        crops, depth, tilt, target = samples.batch(idx[start:start + 512], config.dexnet)
        logits = model(crops, depth, tilt)
        losses.append(F.binary_cross_entropy_with_logits(logits, target, reduction="none").numpy())
        probs.append(torch.sigmoid(logits).numpy())
        targets.append(target.numpy())
    loss, p, t = np.concatenate(losses), np.concatenate(probs), np.concatenate(targets)
    pos = t >= config.positive_threshold
    hit = (p >= config.positive_threshold) == pos
    classes = [mask for mask in (pos, ~pos) if mask.any()]
    return {"loss": float(loss.mean()), "balanced_loss": float(np.mean([loss[m].mean() for m in classes])),
            "balanced_accuracy": float(np.mean([hit[m].mean() for m in classes])),
            "positives": int(pos.sum()), "samples": len(idx)}


def train(records: Sequence[Mapping[str, np.ndarray]], config: TrainConfig, out: str | Path | None = None,
          metadata: Mapping[str, Any] | None = None, progress: bool = True,
          started: float | None = None) -> tuple[SuctionQualityNet, dict[str, Any]]:
    """Train on scene records; return the model (best class-balanced validation loss, or the last epoch
    without validation)
    and a history with the initial and final training loss on a fixed balanced subset.

    The checkpoint's ``provenance`` takes the command and data from ``metadata``; its wall time runs from
    ``started`` (a ``time.perf_counter()``; None: this call's start), so the caller's data loading can count."""
    if len(records) == 0:
        raise ValueError("no scenes to train on")
    rng = np.random.default_rng(config.seed)
    torch.manual_seed(config.seed)
    order = rng.permutation(len(records))
    num_val = int(round(config.val_fraction * len(records))) if len(records) > 1 else 0
    if config.val_fraction > 0 and len(records) > 1:
        num_val = max(num_val, 1)
    train_set = build_samples([records[i] for i in order[num_val:]], config, rng)
    val_set = build_samples([records[i] for i in order[:num_val]], config, rng) if num_val else None
    if len(train_set) == 0:
        raise ValueError("no usable training samples: no annotation point is visible with an eligible approach")

    model = SuctionQualityNet(config.dexnet)
    optimiser = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    steps_per_epoch = -(-config.samples_per_epoch // config.batch_size)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=config.epochs * steps_per_epoch)
    probe = balanced_indices(train_set.target, config.positive_threshold, min(2048, config.samples_per_epoch), rng)
    val_idx = np.arange(len(val_set)) if val_set is not None and len(val_set) else None
    history: dict[str, Any] = {"train_samples": len(train_set), "val_samples": 0 if val_idx is None else len(val_idx),
                               "train_positives": int((train_set.target >= config.positive_threshold).sum()),
                               "epochs": []}
    history["initial_loss"] = evaluate(model, train_set, probe, config)["loss"]
    best_state, best_val = None, float("inf")
    start_time = time.perf_counter()
    for epoch in range(config.epochs):
        model.train()
        idx = balanced_indices(train_set.target, config.positive_threshold, config.samples_per_epoch, rng)
        running, seen = 0.0, 0
        bar = tqdm(range(0, len(idx), config.batch_size), desc=f"epoch {epoch + 1}/{config.epochs}",
                   disable=not progress, leave=False)
        for start in bar:
            crops, depth, tilt, target = train_set.batch(idx[start:start + config.batch_size], config.dexnet)
            flip = torch.from_numpy(rng.random(len(target)) < 0.5)  # mirror across the approach axis
            crops = torch.where(flip[:, None, None, None], crops.flip(2), crops)
            loss = F.binary_cross_entropy_with_logits(model(crops, depth, tilt), target)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            scheduler.step()
            running += loss.item() * len(target)
            seen += len(target)
            bar.set_postfix(loss=f"{running / seen:.4f}")
        entry = {"epoch": epoch + 1, "train_loss": running / max(seen, 1)}
        if val_idx is not None:
            val = evaluate(model, val_set, val_idx, config)
            entry.update(val_loss=val["loss"], val_balanced_loss=val["balanced_loss"],
                         val_balanced_accuracy=val["balanced_accuracy"])
            if val["balanced_loss"] < best_val:
                best_val = val["balanced_loss"]
                best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        history["epochs"].append(entry)
        tqdm.write("  ".join(f"{k}={v:.4f}" if isinstance(v, float) else f"{k}={v}" for k, v in entry.items()))
    history["train_seconds"] = time.perf_counter() - start_time
    history["final_loss"] = evaluate(model, train_set, probe, config)["loss"]
    if best_state is not None:
        model.load_state_dict(best_state)
        history["best_val_balanced_loss"] = best_val
    model.eval()
    if out is not None:
        meta = {**dict(metadata or {}), "train_config": _train_config_dict(config), "history": history}
        meta["provenance"] = training_provenance(meta.get("command", NOT_RECORDED), config.seed, meta.get("data"),
                                                 start_time if started is None else started)
        save_checkpoint(out, model, meta)
    return model, history


def _train_config_dict(config: TrainConfig) -> dict[str, Any]:
    return {k: v for k, v in vars(config).items() if k != "dexnet"}


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    defaults = TrainConfig()
    parser = argparse.ArgumentParser(prog="python -m policies.dexnet.train", description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="dataset directory made by `python -m dataset.generate`")
    parser.add_argument("--out", required=True, help="checkpoint path to write")
    parser.add_argument("--epochs", type=int, default=defaults.epochs)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--batch-size", type=int, default=defaults.batch_size)
    parser.add_argument("--lr", type=float, default=defaults.lr)
    parser.add_argument("--samples-per-epoch", type=int, default=defaults.samples_per_epoch)
    parser.add_argument("--max-points-per-scene", type=int, default=defaults.max_points_per_scene)
    parser.add_argument("--val-fraction", type=float, default=defaults.val_fraction)
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    parser.add_argument("--no-progress", action="store_true", help="hide the tqdm bars (epoch summaries stay)")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    started = time.perf_counter()
    check_input_dir(args.data, "--data")
    check_output_path(args.out, "--out")
    if args.threads is not None:
        if args.threads < 1:
            raise SystemExit(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    try:
        config = replace(TrainConfig(), epochs=args.epochs, seed=args.seed, batch_size=args.batch_size, lr=args.lr,
                         samples_per_epoch=args.samples_per_epoch, max_points_per_scene=args.max_points_per_scene,
                         val_fraction=args.val_fraction)
    except ValueError as exc:
        raise SystemExit(f"error: {exc}") from exc
    records = load_records(args.data)
    command = command_line("policies.dexnet.train", argv)
    from dataset.suctionnet.views import store_config

    metadata = {"command": command, "data": str(args.data), "num_scenes": len(records),
                "dataset_config": store_config(args.data)}
    _, history = train(records, config, out=args.out, metadata=metadata, progress=not args.no_progress,
                       started=started)
    print(f"trained on {history['train_samples']} samples ({history['train_positives']} positive) from "
          f"{len(records)} scenes in {history['train_seconds']:.1f} s; loss {history['initial_loss']:.4f} -> "
          f"{history['final_loss']:.4f}; wrote {args.out} ({Path(args.out).stat().st_size / 1e6:.2f} MB)")
    return history


if __name__ == "__main__":
    sys.exit(run_cli(main))
