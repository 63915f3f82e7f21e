"""End-to-end dataset generation speed: scenes/minute, annotations/second, time per stage, peak RSS.

    .venv/bin/python benchmarks/bench_dataset.py            # 30-parcel stacked mixed, 16,384 pts, 640x480
    .venv/bin/python benchmarks/bench_dataset.py --scenes 2 --workers 1

Each worker count runs in a fresh subprocess (so its peak RSS and start-up cost are its own) through
the real CLI code path, `dataset.generate.generate`, local backend. ``wall s/scene/core`` = wall *
workers / scenes includes start-up and any contention from other jobs on the machine; CPU seconds
(all threads, driver + workers, from getrusage) do not grow with contention, so the extrapolation
uses them. The load average is printed so a reader can tell how busy the machine was.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

PAPER_SCENES = 25_000
GOAL_S_PER_SCENE_CORE = 3.0
RESULT_TAG = "BENCH_RESULT "  # pybullet's C code also writes to stdout


def _config(args: argparse.Namespace, scenes: int):
    from dataset.config import GenerationConfig

    return GenerationConfig(scenes=scenes, seed=args.seed, min_parcels=args.parcels, max_parcels=args.parcels,
                            layout="stacked", object_set="mixed", annotation_points=args.points, width=args.width,
                            height=args.height, scenes_per_shard=scenes)


def _child(args: argparse.Namespace) -> None:
    from dataset.generate import generate

    config = _config(args, args.scenes * args.run_workers)
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        report = generate(out, config, workers=args.run_workers, progress=False)
        wall = time.perf_counter() - start
        size = sum(p.stat().st_size for p in Path(out).glob("*.h5"))
        from dataset.storage import open_dataset

        store = open_dataset(out)
        parcels = [int(store.scene(i, ["num_parcels"])["num_parcels"]) for i in range(len(store))]
    print(RESULT_TAG + json.dumps({
        "workers": args.run_workers, "scenes": report.scenes_generated, "wall": wall,
        "stages": report.stage_seconds, "bytes": size,
        "parcels": sum(parcels) / len(parcels),
        "cpu": sum(getattr(resource.getrusage(who), f) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
                   for f in ("ru_utime", "ru_stime")),
        "rss_self_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "rss_children_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
    }))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=3, help="scenes per worker for each run")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--parcels", type=int, default=30)
    parser.add_argument("--points", type=int, default=16384)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--run-workers", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.run_workers is not None:
        _child(args)
        return

    load_before = os.getloadavg()[0]
    rows = []
    for workers in args.workers:
        cmd = [sys.executable, __file__, "--run-workers", str(workers), "--scenes", str(args.scenes),
               "--parcels", str(args.parcels), "--points", str(args.points), "--width", str(args.width),
               "--height", str(args.height), "--seed", str(args.seed)]
        done = subprocess.run(cmd, check=True, capture_output=True, text=True)
        tagged = [line for line in done.stdout.splitlines() if line.startswith(RESULT_TAG)]
        rows.append(json.loads(tagged[-1][len(RESULT_TAG):]))

    stages = ("pile", "render", "fps", "scoring", "write")
    print(f"\n### Dataset generation: {args.parcels}-parcel stacked mixed scenes, {args.points} points, "
          f"{args.width}x{args.height} (load average before/after: {load_before:.1f} / {os.getloadavg()[0]:.1f})\n")
    print("| workers | scenes | parcels kept | wall s | scenes/min | annotations/s | wall s/scene/core "
          "| CPU s/scene | MB/scene | peak RSS MB (driver / worker) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        n, w = r["scenes"], r["workers"]
        worker_rss = r["rss_children_mb"] if w > 1 else r["rss_self_mb"]
        print(f"| {w} | {n} | {r['parcels']:.1f} | {r['wall']:.1f} | {60 * n / r['wall']:.2f} "
              f"| {n * args.points / r['wall']:.0f} | {r['wall'] * w / n:.2f} | {r['cpu'] / n:.2f} "
              f"| {r['bytes'] / n / 1e6:.2f} | {r['rss_self_mb']:.0f} / {worker_rss:.0f} |")
    print("\nPer scene, by stage: wall s / CPU s\n")
    print("| workers | " + " | ".join(stages) + " |")
    print("|---|" + "---|" * len(stages))
    for r in rows:
        st, n = r["stages"], r["scenes"]
        print(f"| {r['workers']} | " + " | ".join(f"{st.get(s, 0.0) / n:.2f} / {st.get(s + '_cpu', 0.0) / n:.2f}"
                                                  for s in stages) + " |")
    best = max(rows, key=lambda r: r["scenes"] / r["wall"])
    cpu_scene = sum(best["stages"].get(s + "_cpu", 0.0) for s in stages) / best["scenes"]
    verdict = "meets" if cpu_scene <= GOAL_S_PER_SCENE_CORE else "misses"
    print(f"\nSteady-state cost: {cpu_scene:.2f} CPU s/scene (sum of stage CPU, no start-up); "
          f"goal <= {GOAL_S_PER_SCENE_CORE:.1f} s/scene/core: {verdict} it.")
    print(f"{PAPER_SCENES} scenes here: {PAPER_SCENES * best['wall'] / best['scenes'] / 3600:.1f} h at the measured "
          f"wall rate ({best['workers']} workers); {PAPER_SCENES * cpu_scene / 2 / 3600:.1f} h on 2 idle cores.")
    print(f"On a C-core Ray cluster: T(C) ~= {PAPER_SCENES} * {cpu_scene:.2f} s / C + start-up (scenes are "
          f"independent, so scaling is ~linear): "
          + ", ".join(f"C={c}: {PAPER_SCENES * cpu_scene / c / 3600:.2f} h" for c in (16, 64, 256)))


if __name__ == "__main__":
    main()
