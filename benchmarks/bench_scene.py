"""Scene benchmark: what a pile request keeps, how long building it takes, and the env reset at 30 parcels.

Prints two markdown tables:
- per layout and N (10, 30, 50; mixed object set by default): parcels kept / asked (mean and range over
  the seeds), skipped (no room, scattered) and lost (settled outside the tote), the hull fill asked and kept
  (the parcels' convex-hull volume over the tote's, ``pile.hull_fill``), build + settle wall and CPU time
  (median), simulated steps, and how many piles ended at rest;
- ``ParcelPickEnv.reset`` at ``--reset-parcels`` stacked parcels (pile build, arm, settle against the
  arm, first capture at the env's default 640x480 camera): median wall time, and the pile build's share.
Run: ``.venv/bin/python benchmarks/bench_scene.py [--runs 5] [--objects mixed] [--reset-runs 3]``; ``--wall-height``,
``--layouts`` and ``--counts`` ask what another tote would keep (``--wall-height 0.5 --layouts stacked --counts 50``),
``--heavy-first KG`` what another induction order would, ``--split test`` what the held-out assets keep.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from parcelpick_env.assets.library import OBJECT_SETS, AssetLibrary  # noqa: E402
from parcelpick_env.scene.config import LAYOUTS, PileConfig  # noqa: E402
from parcelpick_env.scene.pile import build_pile, hull_fill  # noqa: E402
from parcelpick_env.scene.scene import BinSpec  # noqa: E402
from parcelpick_env.sim.config import SimConfig  # noqa: E402
from parcelpick_env.sim.simulator import Simulator  # noqa: E402

COUNTS = (10, 30, 50)


def _timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def _pile_rows(object_sets: list[str], runs: int, library: AssetLibrary, spec: BinSpec,
               layouts: tuple[str, ...] = LAYOUTS, counts: tuple[int, ...] = COUNTS,
               heavy_first_mass: float | None = None, split: str = "train") -> list[str]:
    rows = []
    with Simulator(SimConfig(egl_rendering=False)) as sim:
        for object_set in object_sets:
            for layout in layouts:
                for n in counts:
                    config = PileConfig(num_parcels=n, layout=layout, object_set=object_set, bin=spec,
                                        heavy_first_mass=heavy_first_mass, split=split)
                    kept, skipped, lost, walls, cpus, steps, rest = [], [], [], [], [], [], 0
                    asked_fill, kept_fill = [], []  # hull volume over the tote's: asked, and in the tote
                    for seed in range(runs):
                        scene, wall, cpu = _timed(lambda: build_pile(sim, config, seed=seed, library=library))
                        kept.append(len(scene.parcels))
                        skipped.append(scene.meta["skipped"])
                        lost.append(scene.meta["lost"])
                        walls.append(wall)
                        cpus.append(cpu)
                        steps.append(scene.meta["settle_steps"])
                        rest += bool(scene.meta["at_rest"])
                        asked_fill.append(scene.meta["hull_fill"])
                        kept_fill.append(hull_fill([parcel.asset for parcel in scene.parcels], spec))
                    rows.append(f"| {object_set} | {layout} | {n} | {np.mean(kept):.1f} / {n} ({100 * np.mean(kept) / n:.0f}%) "
                                f"| {min(kept)}-{max(kept)} | {np.mean(skipped):.1f} | {np.mean(lost):.1f} "
                                f"| {np.mean(asked_fill):.2f} | {np.mean(kept_fill):.2f} "
                                f"| {statistics.median(walls):.2f} | {statistics.median(cpus):.2f} "
                                f"| {statistics.median(steps):.0f} | {rest}/{runs} |")
                    print(rows[-1], file=sys.stderr, flush=True)
    return rows


def _reset_rows(parcels: int, runs: int) -> list[str]:
    from parcelpick_env.envs.parcel_pick import ParcelPickEnv

    env = ParcelPickEnv(num_parcels=parcels, layout="stacked", object_set="mixed")
    from parcelpick_env.scene import pile

    build_times: list[float] = []
    original = pile.build_pile

    def timed_build(*args, **kwargs):
        scene, wall, _ = _timed(lambda: original(*args, **kwargs))
        build_times.append(wall)
        return scene

    pile.build_pile = timed_build
    resets, kept = [], []
    try:
        env.reset(seed=1000)  # first reset: EGL, URDF and the asset library load once per process
        build_times.clear()
        for seed in range(runs):
            (_, info), wall, _ = _timed(lambda: env.reset(seed=seed))
            resets.append(wall)
            kept.append(info["parcels_placed"])
    finally:
        pile.build_pile = original
        env.close()
    return [f"| {parcels} stacked mixed, {env.config.camera.width}x{env.config.camera.height} camera | "
            f"{statistics.median(resets):.2f} | {min(resets):.2f}-{max(resets):.2f} | "
            f"{statistics.median(build_times):.2f} | {min(kept)}-{max(kept)} |"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="seeds per (layout, N)")
    parser.add_argument("--objects", default="mixed", help=f"comma-separated object sets, or 'all' ({OBJECT_SETS})")
    parser.add_argument("--reset-parcels", type=int, default=30)
    parser.add_argument("--reset-runs", type=int, default=3, help="env resets timed (0 skips the env)")
    parser.add_argument("--wall-height", type=float, default=BinSpec().wall_height,
                        help="the tote's wall height (m) for the pile rows; the env's reset keeps the cell's own")
    parser.add_argument("--heavy-first", type=float, default=None, metavar="KG",
                        help="stacked pile rows: parcels heavier than KG go down the chute first (PileConfig.heavy_first_mass)")
    parser.add_argument("--layouts", nargs="+", default=list(LAYOUTS), choices=LAYOUTS)
    parser.add_argument("--counts", nargs="+", type=int, default=list(COUNTS), help="parcels asked")
    parser.add_argument("--split", default="train", choices=("train", "test"),
                        help="asset split of the pile rows (the env and the clearance use train; the test data test)")
    args = parser.parse_args()
    object_sets = list(OBJECT_SETS) if args.objects == "all" else args.objects.split(",")
    try:
        spec = BinSpec(wall_height=args.wall_height)
    except ValueError as exc:
        parser.error(f"--wall-height: {exc}")
    try:
        PileConfig(heavy_first_mass=args.heavy_first)
    except ValueError as exc:
        parser.error(f"--heavy-first: {exc}")

    library = AssetLibrary.default(0)
    rows = _pile_rows(object_sets, args.runs, library, spec, tuple(args.layouts), tuple(args.counts),
                      args.heavy_first, args.split)
    order = "" if args.heavy_first is None else f"; parcels over {args.heavy_first:g} kg first"
    print(f"\n### Piles: parcels kept against parcels asked ({args.runs} seeds each; {args.split} assets; tote "
          f"{spec.inner_size[0]:.2f} x {spec.inner_size[1]:.2f} x {spec.wall_height:.2f} m{order})\n")
    print("| object set | layout | asked | kept (mean) | kept (range) | skipped | lost | hull fill asked | "
          "hull fill kept | build+settle wall (s) | CPU (s) | sim steps | at rest |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    if args.reset_runs > 0:
        print(f"\n### ParcelPickEnv.reset, median of {args.reset_runs}\n")
        print("| pile | reset wall (s) | range (s) | of which pile build (s) | parcels kept |")
        print("|---|---|---|---|---|")
        print("\n".join(_reset_rows(args.reset_parcels, args.reset_runs)))


if __name__ == "__main__":
    main()
