"""What centre votes add to a Diffusion-Suction prediction: the shipped ``diffusion`` and ``diffusion_vote`` policies
on the same clouds, and the votes alone (head, clustering, wrench). Prints a markdown table.

    .venv/bin/python benchmarks/bench_centre_vote.py [--threads 2] [--points 4096 16384] [--repeats 5] [--data DIR]
    .venv/bin/python benchmarks/bench_centre_vote.py --views 4   # on ParcelPick-v0's observations, by voters

The clouds are synthetic piles (``policies.diffusion.synthetic``), so the figures do not depend on a dataset; with
``--data``, also the first stored scene's cloud (a real pile, whose votes crowd less than a synthetic one's). With
``--views K``, the policies decide on K of the env's observations, decoding at the depth candidates, with the
votes cast at every decoded point, without the expectation over the votes' spread, without vote segments, and as
shipped.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from policies.diffusion.policy import DiffusionSuctionPolicy  # noqa: E402
from policies.diffusion.synthetic import synthetic_scene  # noqa: E402
from policies.diffusion.vote_policy import DiffusionCentreVotePolicy  # noqa: E402
from timing import time_calls  # noqa: E402


def bench_views(count: int, repeats: int) -> None:
    """Median and p90 of each policy's ``predict`` on ``count`` env views, interleaved call by call."""
    from bench_diffusion import env_views
    from timing import interleaved_times

    views = env_views(count, 4096)
    policies = {"diffusion": DiffusionSuctionPolicy(record_trajectory=False),
                "diffusion_vote, voters=0 (every decoded point)": DiffusionCentreVotePolicy(voters=0,
                                                                                            record_trajectory=False),
                "diffusion_vote, spread_scale=0 (the wrench about the averaged centre)": DiffusionCentreVotePolicy(
                    spread_scale=0.0, record_trajectory=False),
                "diffusion_vote, segment_spacings=0 (the votes' centres, no vote segments)": DiffusionCentreVotePolicy(
                    segment_spacings=0.0, record_trajectory=False)}
    shipped = DiffusionCentreVotePolicy(record_trajectory=False)
    config = shipped.centre_head.config
    policies[f"diffusion_vote, voters={config.voters}, spread_draws={config.spread_draws}, "
             f"segment_spacings={config.segment_spacings:g} (shipped)"] = shipped
    times: dict[str, list[float]] = {name: [] for name in policies}
    for obs, info in views:
        samples = interleaved_times({name: (lambda p=policy: p.predict(obs, info)) for name, policy in policies.items()},
                                    repeats)
        for name in policies:
            times[name] += samples[name]
    print(f"| policy ({count} views, {repeats} calls each) | predict median (ms) | p90 (ms) |")
    print("|---|---|---|")
    for name, values in times.items():
        median, p90 = np.percentile(values, [50, 90])
        print(f"| {name} | {median:.1f} | {p90:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--points", type=int, nargs="+", default=[4096, 16384])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--data", help="also time the first scene of this dataset directory")
    parser.add_argument("--views", type=int, default=0, metavar="K",
                        help="only the policies on K of ParcelPick-v0's observations, at the depth candidates")
    args = parser.parse_args()
    if args.views < 0:
        parser.error(f"--views must be >= 0, got {args.views}")
    torch.set_num_threads(args.threads)
    if args.views:
        bench_views(args.views, args.repeats)
        return
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
        channels = np.ones((len(points), 3), dtype=np.float32)

        def votes_alone() -> None:
            vote.quality(points, normals, features, channels)

        row = [time_calls(lambda: base.predict(obs), args.repeats), time_calls(lambda: vote.predict(obs), args.repeats),
               time_calls(votes_alone, args.repeats)]
        print(f"| {name} | " + " | ".join(f"{v:.1f}" for v in row) + " |")


if __name__ == "__main__":
    main()
