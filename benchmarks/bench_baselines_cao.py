"""Cao et al. baseline speed: inference latency at 640x480 and 160x120, and training time on 2 cores.

    .venv/bin/python benchmarks/bench_baselines_cao.py                 # shipped checkpoint if present
    .venv/bin/python benchmarks/bench_baselines_cao.py --threads 1 2 --runs 20 --train-scenes 64

Latency does not depend on the weights, so without a shipped checkpoint a freshly initialised
network of the default config is timed (the table says which). Observations are synthetic boxes on
a floor under an overhead camera, with a 16,384-point cloud. Training is timed on synthetic tensors
of the default input size with the real optimiser step, and reported per epoch of 100 scenes.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from timing import time_calls  # noqa: E402  (benchmarks/timing.py)


CLOUD_POINTS = 16384  # the observed cloud's size, as in the dataset's stored scenes


def synthetic_observation(width: int, height: int, seed: int = 0) -> tuple[dict, dict]:
    """An overhead view (1 m up, ~60 deg field of view) of a few boxes on a floor."""
    rng = np.random.default_rng(seed)
    f = 0.5 * width / np.tan(np.radians(30))
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[2, 3] = 1.0
    depth = np.full((height, width), 1.0, dtype=np.float32)
    rgb = np.full((height, width, 3), 90, dtype=np.uint8)
    rows, cols = np.mgrid[0:height, 0:width]
    for _ in range(8):
        h0, w0 = (rng.uniform(0.1, 0.3, size=2) * (height, width)).astype(int)
        r0, c0 = rng.integers(0, height - h0), rng.integers(0, width - w0)
        inside = (rows >= r0) & (rows < r0 + h0) & (cols >= c0) & (cols < c0 + w0)
        depth[inside] = 1.0 - rng.uniform(0.05, 0.3)
        rgb[inside] = rng.integers(100, 255, size=3)
    z = depth.ravel().astype(np.float64)
    cam = np.stack([(cols.ravel() - K[0, 2]) * z / f, (rows.ravel() - K[1, 2]) * z / f, z], axis=1)
    points = (cam @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    points = points[rng.choice(len(points), size=min(len(points), CLOUD_POINTS), replace=False)]
    normals = np.tile(np.array([0, 0, 1], dtype=np.float32), (len(points), 1))
    return {"rgb": rgb, "depth": depth[..., None], "points": points, "normals": normals}, \
        {"intrinsics": K, "extrinsics": T}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[2], help="torch CPU thread counts to time")
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--train-scenes", type=int, default=32, help="synthetic scenes for the training timing")
    parser.add_argument("--checkpoint", default=None, help="default: the shipped policies/cao/checkpoint.pt")
    args = parser.parse_args()

    from policies.cao.config import CaoConfig
    from policies.cao.network import CaoNet
    from policies.cao.policy import DEFAULT_CHECKPOINT, CaoPolicy
    from policies.cao.train import _random_flips, heatmap_loss

    checkpoint = Path(args.checkpoint) if args.checkpoint else DEFAULT_CHECKPOINT
    tmp = tempfile.TemporaryDirectory()
    weights = "shipped checkpoint" if checkpoint.is_file() else "random init (no checkpoint shipped)"
    if not checkpoint.is_file():
        checkpoint = Path(tmp.name) / "random.pt"
        torch.manual_seed(0)
        torch.save({"config": CaoConfig().to_dict(), "state_dict": CaoNet(CaoConfig()).state_dict()}, checkpoint)
    policy = CaoPolicy(checkpoint=checkpoint, threads=None)  # the loop below sets torch's thread count
    config = policy.config
    params = sum(p.numel() for p in policy.net.parameters())

    print(f"## Cao et al. baseline (torch {torch.__version__}, {weights}, {params / 1e3:.0f}k params, "
          f"net input {config.input_width}x{config.input_height}; median of {args.runs} runs)\n")
    print("| threads | observation | heatmaps (ms) | predict top-50 (ms) |")
    print("|---|---|---|---|")
    for threads in args.threads:
        torch.set_num_threads(threads)
        for width, height in ((640, 480), (160, 120)):
            obs, info = synthetic_observation(width, height)
            heat = time_calls(lambda: policy.heatmaps(obs, info), args.runs)
            full = time_calls(lambda: policy.predict(obs, info, top_k=50), args.runs)
            print(f"| {threads} | {width}x{height} | {heat:.1f} | {full:.1f} |")

    net = CaoNet(config)
    optimiser = torch.optim.AdamW(net.parameters(), lr=config.learning_rate)
    generator = torch.Generator().manual_seed(0)
    x = torch.randn(args.train_scenes, 4, config.input_height, config.input_width, generator=generator)
    y = torch.rand(args.train_scenes, 2, config.input_height, config.input_width, generator=generator)

    def epoch() -> None:  # the loop of policies.cao.train.train, on random tensors
        net.train()
        for start in range(0, len(x), config.batch_size):
            xb, yb = _random_flips(x[start:start + config.batch_size], y[start:start + config.batch_size], generator)
            loss = heatmap_loss(net(xb), yb)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()

    print(f"\n| threads | training step (batch {config.batch_size}, {config.input_width}x{config.input_height}) "
          f"| epoch of 100 scenes | default run ({config.epochs} epochs x 100 scenes) |")
    print("|---|---|---|---|")
    for threads in args.threads:
        torch.set_num_threads(threads)
        seconds = time_calls(epoch, max(1, args.runs // 5)) / 1e3
        per_100 = seconds * 100 / args.train_scenes
        step_ms = seconds / -(-args.train_scenes // config.batch_size) * 1e3
        print(f"| {threads} | {step_ms:.0f} ms | {per_100:.1f} s | {per_100 * config.epochs / 60:.1f} min |")
    print(f"\npeak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    tmp.cleanup()


if __name__ == "__main__":
    main()
