"""What centre votes add to a Diffusion-Suction prediction: the shipped ``diffusion`` and ``diffusion_vote`` policies
on the same clouds, and the votes alone (head, clustering, wrench). Prints a markdown table.

    .venv/bin/python benchmarks/bench_centre_vote.py [--threads 2] [--points 4096 16384] [--repeats 5] [--data DIR]

The clouds are synthetic piles (``policies.diffusion.synthetic``), so the figures do not depend on a dataset; with
``--data``, also the first stored scene's cloud (a real pile, whose votes crowd less than a synthetic one's).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from policies.diffusion.centre_vote import cluster_centres, vote_wrench  # noqa: E402
from policies.diffusion.policy import DiffusionSuctionPolicy  # noqa: E402
from policies.diffusion.synthetic import synthetic_scene  # noqa: E402
from policies.diffusion.vote_policy import DiffusionCentreVotePolicy  # noqa: E402


def median_ms(run, repeats: int) -> float:
    run()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--points", type=int, nargs="+", default=[4096, 16384])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--data", help="also time the first scene of this dataset directory")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    base = DiffusionSuctionPolicy(record_trajectory=False)
    vote = DiffusionCentreVotePolicy(record_trajectory=False)
    print("| input points | diffusion predict (ms) | diffusion_vote predict (ms) | votes alone (ms) |")
    print("|---|---|---|---|")
    clouds = [(f"{n} (synthetic)", synthetic_scene(np.random.default_rng(0), n)) for n in args.points]
    if args.data:
        from dataset.storage import open_dataset

        store = open_dataset(args.data)
        record = store.scene(0, ("points", "normals"))
        store.close()
        clouds.append((f"{len(record['points'])} ({args.data}, scene 0)", record))
    for name, scene in clouds:
        obs = {"points": np.asarray(scene["points"], np.float32), "normals": np.asarray(scene["normals"], np.float32)}
        points, normals = obs["points"][: base.config.num_points], obs["normals"][: base.config.num_points]
        features = base.encode_cloud(points, normals)[0]
        head = vote.centre_head

        def votes_alone() -> None:
            with torch.inference_mode():
                offsets = head(features, torch.from_numpy(np.ascontiguousarray(normals))).numpy()
            centres = cluster_centres(points + offsets, head.config.cluster_radius, head.config.cluster_neighbours)
            vote_wrench(points, normals, centres, head.config.wrench_definition)

        row = [median_ms(lambda: base.predict(obs), args.repeats), median_ms(lambda: vote.predict(obs), args.repeats),
               median_ms(votes_alone, args.repeats)]
        print(f"| {name} | " + " | ".join(f"{v:.1f}" for v in row) + " |")


if __name__ == "__main__":
    main()
