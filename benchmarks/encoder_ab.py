"""Diffusion-Suction encoder speed of two source trees, interleaved in one process on the same inputs and weights.

A shared VM's speed drifts by 20-50% between runs, so two separate ``bench_diffusion.py`` runs cannot resolve a
change of that size; alternating the trees call by call can. Each tree is imported in turn (its ``policies``
package replaces the previous one's), builds the same seeded model and neighbourhoods, and the outputs are compared.

    .venv/bin/python benchmarks/encoder_ab.py BEFORE_TREE AFTER_TREE [--preset paper|cpu] [--repeats 10]

A tree is a checkout of this repository, e.g. ``git worktree add /tmp/before HEAD~1``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch


def load_encoder(tree: Path, preset: str) -> Callable[[], torch.Tensor]:
    """The folded encoder of ``tree`` on a fixed synthetic scene, as a zero-argument call."""
    for name in [m for m in sys.modules if m == "policies" or m.startswith("policies.")]:
        del sys.modules[name]
    sys.path.insert(0, str(tree))
    try:
        from policies.diffusion.config import DiffusionConfig
        from policies.diffusion.model import build_model
        from policies.diffusion.neighbourhood import model_inputs
        from policies.diffusion.pointnet2 import fold_batchnorm
        from policies.diffusion.synthetic import synthetic_scene
    finally:
        sys.path.pop(0)
    cfg = DiffusionConfig.cpu() if preset == "cpu" else DiffusionConfig()
    model = build_model(cfg, seed=0).eval()
    encoder = fold_batchnorm(model.encoder)
    scene = synthetic_scene(np.random.default_rng(0), cfg.num_points)
    inputs: dict[str, Any] = {**scene, **model_inputs(scene["points"], scene["normals"], cfg)}
    batch = {k: torch.from_numpy(np.asarray(v)).unsqueeze(0) for k, v in inputs.items()}
    return lambda: encoder(batch)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("before", type=Path)
    p.add_argument("after", type=Path)
    p.add_argument("--preset", choices=("paper", "cpu"), default="paper")
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    for tree in (args.before, args.after):
        if not (tree / "policies" / "diffusion" / "pointnet2.py").is_file():
            p.error(f"{tree}: not a ParcelPick source tree (no policies/diffusion/pointnet2.py)")
    torch.set_num_threads(args.threads)
    runs = {"before": load_encoder(args.before, args.preset), "after": load_encoder(args.after, args.preset)}
    times: dict[str, list[float]] = {k: [] for k in runs}
    with torch.inference_mode():
        out = {k: run() for k, run in runs.items()}  # also the warm-up
        for _ in range(args.repeats):
            for k, run in runs.items():
                start = time.perf_counter()
                run()
                times[k].append(1000 * (time.perf_counter() - start))
    diff = float((out["before"] - out["after"]).abs().max())
    print(f"### Encoder A/B, {args.preset} preset, {args.threads} threads, median of {args.repeats} interleaved calls\n")
    print("| tree | path | median ms | min ms |\n|---|---|---|---|")
    for k, path in (("before", args.before), ("after", args.after)):
        print(f"| {k} | {path} | {statistics.median(times[k]):.1f} | {min(times[k]):.1f} |")
    print(f"\nmax |before - after| over the features: {diff:.2e}")


if __name__ == "__main__":
    main()
