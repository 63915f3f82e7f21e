"""Dex-Net 3.0 style baseline speed: inference latency at 640x480 and 160x120, training time on 2 cores.

    .venv/bin/python benchmarks/bench_baselines_dexnet.py
    .venv/bin/python benchmarks/bench_baselines_dexnet.py --threads 2 --runs 5 --data data/train160

Observations are real captures of a settled 20-parcel mixed pile (the project's simulator and camera),
with the full camera cloud (every valid pixel) as ``obs['points']``. Latency does not depend on the
weights, so without a shipped checkpoint a freshly initialised default network is timed (the table
says which). Training is timed for one epoch of the default TrainConfig (its cost is fixed by
``samples_per_epoch`` and the validation split, not by what the scenes hold) on ``--data``, or on a
small dataset made with the dataset pipeline in a temporary directory, and extrapolated to the
default number of epochs.
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from timing import time_calls  # noqa: E402  (benchmarks/timing.py)


def pile_observation(width: int, height: int, seed: int = 0) -> tuple[dict, dict]:
    from parcelpick_env.assets.library import AssetLibrary
    from parcelpick_env.camera.camera import Camera
    from parcelpick_env.camera.config import CameraConfig
    from parcelpick_env.scene.config import PileConfig
    from parcelpick_env.scene.pile import build_pile
    from parcelpick_env.sim.simulator import Simulator

    sim = Simulator()
    try:
        scene = build_pile(sim, PileConfig(num_parcels=20, layout="stacked", object_set="mixed"), seed=seed,
                           library=AssetLibrary.default(seed=0))
        frame = Camera(CameraConfig(width=width, height=height)).capture(sim, scene, np.random.default_rng(seed))
    finally:
        sim.close()
    obs = {"rgb": frame.rgb, "depth": frame.depth[..., None], "points": frame.points, "normals": frame.normals}
    return obs, {"intrinsics": frame.intrinsics, "extrinsics": frame.extrinsics}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--data", default=None, help="dataset directory for the training timing (default: make 6 "
                                                     "scenes at 160x120 with the dataset pipeline)")
    parser.add_argument("--checkpoint", default=None, help="default: the shipped policies/dexnet/checkpoint.pt")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    from policies.dexnet.config import DexNetConfig, TrainConfig
    from policies.dexnet.network import SuctionQualityNet, save_checkpoint
    from policies.dexnet.policy import DEFAULT_CHECKPOINT, DexNetPolicy
    from policies.dexnet.train import load_records, train

    tmp = tempfile.TemporaryDirectory()
    checkpoint = Path(args.checkpoint) if args.checkpoint else DEFAULT_CHECKPOINT
    weights = "shipped checkpoint" if checkpoint.is_file() else "random init (no checkpoint shipped)"
    if not checkpoint.is_file():
        torch.manual_seed(0)
        checkpoint = Path(tmp.name) / "random.pt"
        save_checkpoint(checkpoint, SuctionQualityNet(DexNetConfig()))
    policy = DexNetPolicy(checkpoint=checkpoint, seed=0)
    cfg = policy.config
    params = sum(p.numel() for p in policy.model.parameters())
    print(f"## Dex-Net 3.0 style baseline ({args.threads} threads, torch {torch.__version__}, {weights}, "
          f"{params / 1e3:.0f}k params, {checkpoint.stat().st_size / 1e6:.2f} MB checkpoint)\n")
    print(f"CEM: {cfg.num_seeds} seeds, {cfg.cem_iterations} x {cfg.num_gmm_samples} GMM samples; "
          f"crops {cfg.crop_size}x{cfg.crop_size} over {cfg.crop_metric_size * 100:.0f} cm\n")
    print("| observation | cloud points | eligible | crops scored | crop+CNN, 250 seeds (ms) | predict top-50 (ms) |")
    print("|---|---|---|---|---|---|")
    for width, height in ((640, 480), (160, 120)):
        obs, info = pile_observation(width, height)
        depth = obs["depth"][..., 0]
        K, T = info["intrinsics"], info["extrinsics"]
        cand = policy.eligible(depth, obs["points"].astype(np.float64), obs["normals"].astype(np.float64), K, T)
        from policies.dexnet.crops import DepthMosaic

        seeds = np.arange(min(cfg.num_seeds, len(cand)))
        score = time_calls(lambda: policy.score(DepthMosaic(depth), cand, seeds, K), args.runs)
        policy.reset(0)
        scored = len(policy.search(depth, cand, K)[0])
        full = time_calls(lambda: policy.predict(obs, info, top_k=50), args.runs)
        print(f"| {width}x{height} | {len(obs['points'])} | {len(cand)} | {scored} | {score:.0f} | {full:.0f} |")

    data = args.data
    if data is None:
        from dataset.config import GenerationConfig
        from dataset.generate import generate

        data = Path(tmp.name) / "data"
        generate(data, GenerationConfig(scenes=6, split="train", seed=0, width=160, height=120,
                                        annotation_points=1024), progress=False)
    records = load_records(data)
    default = TrainConfig()
    start = time.perf_counter()
    _, history = train(records, dataclasses.replace(default, epochs=1), progress=False)
    epoch_s = time.perf_counter() - start
    steps = -(-default.samples_per_epoch // default.batch_size)
    print("\n| training (default TrainConfig) | value |")
    print("|---|---|")
    print(f"| data | {len(records)} scenes, {history['train_samples']} train / {history['val_samples']} val samples |")
    print(f"| one epoch: {default.samples_per_epoch} samples, {steps} steps of {default.batch_size}, with validation "
          f"| {epoch_s:.1f} s |")
    print(f"| default run: {default.epochs} epochs | {epoch_s * default.epochs / 60:.1f} min (extrapolated) |")
    print(f"\npeak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
