"""Evaluation throughput: closed-loop clearance attempts per second (1 and 2 workers) and AP time per scene.

    .venv/bin/python benchmarks/bench_eval.py [--policy normal_std] [--episodes 2] [--parcels 6] [--ap-data data/test]

Clearance runs the same grid with 1 and 2 workers (same seeds, so the same attempts); AP timing needs a
dataset made by ``python -m dataset.generate --split test`` and is skipped with a note when there is none.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from eval.clearance import ClearanceConfig, evaluate_clearance  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policy", default="normal_std")
    ap.add_argument("--episodes", type=int, default=2)
    ap.add_argument("--parcels", type=int, default=6)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--ap-data", default="data/test")
    ap.add_argument("--ap-scenes", type=int, default=6)
    args = ap.parse_args(argv)

    print(f"## Clearance throughput ({args.policy}, mixed/stacked, {args.episodes} episodes x {args.parcels} parcels)\n")
    print("| workers | wall s | attempts | attempts/s | episodes/min | R_grasp % | R_object % |")
    print("|---|---|---|---|---|---|---|")
    for workers in args.workers:
        config = ClearanceConfig(policy=args.policy, objects=("mixed",), layouts=("stacked",),
                                 episodes=args.episodes, num_parcels=args.parcels, workers=workers)
        start = time.perf_counter()
        summary = evaluate_clearance(config, progress=False)
        wall = time.perf_counter() - start
        o = summary["overall"]
        print(f"| {workers} | {wall:.1f} | {o['attempts']} | {o['attempts'] / wall:.3f} | "
              f"{60 * args.episodes / wall:.2f} | {o['R_grasp']:.1f} | {o['R_object']:.1f} |")

    data = Path(args.ap_data)
    if (data / "manifest.json").is_file():
        from eval.ap import evaluate_ap

        print(f"\n## Offline AP time per scene ({data}, {args.ap_scenes} scenes)\n")
        print("| policy | s/scene | AP |")
        print("|---|---|---|")
        for policy in ("random", args.policy):
            start = time.perf_counter()
            result = evaluate_ap(policy, data, scenes=args.ap_scenes)
            per_scene = (time.perf_counter() - start) / max(result["num_scenes"], 1)
            print(f"| {policy} | {per_scene:.2f} | {result['AP']:.2f} |")
    else:
        print(f"\n(AP timing skipped: no dataset at {data}; make one with `python -m dataset.generate --split test`)")
    print(f"\nPeak RSS (this process): {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB; "
          f"workers: {resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
