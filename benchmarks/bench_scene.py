"""Scene benchmark: build + settle a 30-parcel stacked mixed pile, then capture it at 640x480.

Prints a markdown table: median wall and CPU time over a few seeds, settle steps, parcels kept,
capture time (EGL or TinyRenderer, with each normal estimator, and the bare render), points in
the cloud, peak RSS. The default bin cannot hold 30 parcels of the library's sizes, so a larger
bin (framed by ``CameraConfig.for_bin``) is measured too.
Run: ``.venv/bin/python benchmarks/bench_scene.py [--runs 3] [--parcels 30]``.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time

import numpy as np

from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.camera.camera import Camera
from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.scene.config import PileConfig
from parcelpick_env.scene.pile import build_pile
from parcelpick_env.scene.scene import BinSpec
from parcelpick_env.sim.simulator import Simulator

BINS = {
    "default 0.70x0.50 m": BinSpec(),
    "large 1.20x0.90 m": BinSpec(inner_size=(1.2, 0.9), wall_height=0.35),
}


def _timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--parcels", type=int, default=30)
    args = parser.parse_args()

    _, lib_wall, _ = _timed(lambda: AssetLibrary.generate(seed=0))
    library = AssetLibrary.default(0)
    rows = []
    with Simulator() as sim:
        for name, spec in BINS.items():
            config = PileConfig(num_parcels=args.parcels, layout="stacked", object_set="mixed", bin=spec)
            cams = {m: Camera(CameraConfig.for_bin(spec, normal_method=m)) for m in ("open3d", "organized")}
            build, build_cpu, steps, kept = [], [], [], []
            capture = {m: [] for m in cams}
            render = []
            points = 0
            for seed in range(args.runs):
                scene, wall, cpu = _timed(lambda: build_pile(sim, config, seed=seed, library=library))
                build.append(wall)
                build_cpu.append(cpu)
                steps.append(scene.meta["settle_steps"])
                kept.append(len(scene.parcels))
                for method, cam in cams.items():
                    frame, wall, _ = _timed(lambda: cam.capture(sim, scene, np.random.default_rng(seed)))
                    capture[method].append(wall)
                    points = len(frame.points)
                render.append(_timed(lambda: cams["open3d"]._render(sim))[1])
            rows.append((name, statistics.median(build), statistics.median(build_cpu), statistics.median(steps),
                         f"{min(kept)}-{max(kept)}", statistics.median(capture["open3d"]),
                         statistics.median(capture["organized"]), statistics.median(render),
                         cams["open3d"].renderer, points))

    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\n### Scene: {args.parcels} stacked mixed parcels, median of {args.runs} seeds "
          f"(asset library generation: {lib_wall:.2f} s)\n")
    print("| bin | build+settle wall (s) | build+settle CPU (s) | settle steps | parcels kept | "
          "capture 640x480, Open3D normals (s) | capture, organized normals (s) | of which render (s) | renderer | "
          "points | peak RSS (MB) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]:.2f} | {r[2]:.2f} | {r[3]:.0f} | {r[4]} | {r[5]:.3f} | {r[6]:.3f} | {r[7]:.3f} | "
              f"{r[8]} | {r[9]} | {peak_mb:.0f} |")


if __name__ == "__main__":
    main()
