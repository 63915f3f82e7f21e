"""Suction scorer throughput on a 30-parcel stacked pile: candidates/second per score.

Usage: python benchmarks/bench_scorer.py [--candidates 16384] [--parcels 30] [--repeats 3]
       [--threads 0] [--synthetic]

The pile comes from ``parcelpick_env.scene.pile.build_pile`` (pybullet settles it) unless
``--synthetic`` is given or the simulator is unavailable, in which case 30 random boxes are
stacked analytically. Candidates are what an overhead camera sees: the camera module's point
cloud when it exists, else an Open3D ray cast of a 640x480 overhead view (exact normals).
Prints a markdown table and the peak RSS.
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from parcelpick_env.envs.config import EnvConfig  # noqa: E402
from parcelpick_env.scene.scene import BinSpec  # noqa: E402
from parcelpick_env.suction.config import SuctionConfig  # noqa: E402
from parcelpick_env.suction.geometry import O3D_INVALID_ID, build_scene  # noqa: E402
from parcelpick_env.suction.scorer import SuctionScorer  # noqa: E402
from parcelpick_env.suction.visibility import camera_rays, object_visibility  # noqa: E402

WIDTH, HEIGHT = 640, 480
BELLOWS_RADIUS = 0.025  # the 50 mm bellows cup of docs/cup_seal.md


def overhead_camera(bin_spec: BinSpec, height: float = 1.2) -> tuple[np.ndarray, np.ndarray]:
    """A 640x480 OpenCV pinhole looking straight down at the bin centre."""
    K = np.array([[560.0, 0, (WIDTH - 1) / 2], [0, 560.0, (HEIGHT - 1) / 2], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = (*bin_spec.center_xy, bin_spec.floor_z + height)
    return K, T


def synthetic_pile(num: int, rng: np.random.Generator, bin_spec: BinSpec):
    """Random boxes dropped on a height map of the bin: a stand-in when pybullet is not wanted."""
    meshes, coms = [], []
    heights = {}
    cell = 0.05
    for _ in range(num):
        ext = rng.uniform([0.05, 0.05, 0.02], [0.30, 0.25, 0.15])
        half = np.array(bin_spec.inner_size) / 2 - ext[:2] / 2
        xy = rng.uniform(-half, half)
        cells = [(i, j) for i in range(int((xy[0] - ext[0] / 2) // cell), int((xy[0] + ext[0] / 2) // cell) + 1)
                 for j in range(int((xy[1] - ext[1] / 2) // cell), int((xy[1] + ext[1] / 2) // cell) + 1)]
        base = max(heights.get(c, 0.0) for c in cells)
        for c in cells:
            heights[c] = base + ext[2]
        mesh = trimesh.creation.box(extents=ext)
        mesh.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(-0.1, 0.1), (0, 0, 1)))
        mesh.apply_translation((xy[0], xy[1], base + ext[2] / 2))
        meshes.append(mesh)
        coms.append(mesh.centroid)
    return meshes, np.array(coms), bin_spec.meshes()


def load_pile(num: int, seed: int, synthetic: bool):
    """(meshes, coms, obstacles, bin, description, camera frame or None)."""
    if not synthetic:
        try:
            from parcelpick_env.scene.config import PileConfig
            from parcelpick_env.scene.pile import build_pile
            from parcelpick_env.sim.simulator import Simulator

            with Simulator() as sim:
                scene = build_pile(sim, PileConfig(num_parcels=num, layout="stacked", object_set="mixed"), seed)
                frame = None
                try:
                    from parcelpick_env.camera.camera import Camera
                    from parcelpick_env.camera.config import CameraConfig

                    frame = Camera(CameraConfig()).capture(sim, scene, np.random.default_rng(seed))
                except Exception as error:  # noqa: BLE001 - fall back, but say why
                    print(f"Camera unavailable ({type(error).__name__}: {error}); ray casting the view")
            source = (f"build_pile (mixed, stacked, seed {seed}; "
                      f"{scene.meta['lost']} parcels left the bin)")
            return scene.world_meshes(), scene.world_coms(), scene.bin.meshes(), scene.bin, source, frame
        except Exception as error:  # noqa: BLE001 - fall back, but say why
            print(f"build_pile unavailable ({type(error).__name__}: {error}); using a synthetic pile")
    bin_spec = BinSpec()
    return (*synthetic_pile(num, np.random.default_rng(seed), bin_spec), bin_spec, "synthetic boxes", None)


def visible_candidates(meshes, obstacles, K, T, count, rng):
    """Points, exact outward normals and object ids of pixels the overhead camera sees on parcels."""
    rays = camera_rays(K, T, WIDTH, HEIGHT)
    hits = build_scene(list(meshes) + list(obstacles)).cast_rays(o3d.core.Tensor(rays))
    ids = hits["geometry_ids"].numpy().astype(np.int64)
    keep = np.flatnonzero((ids != O3D_INVALID_ID) & (ids < len(meshes)))
    keep = rng.choice(keep, size=count, replace=len(keep) < count)
    origin, directions = rays[keep, :3].astype(np.float64), rays[keep, 3:].astype(np.float64)
    points = origin + hits["t_hit"].numpy()[keep, None].astype(np.float64) * directions
    normals = hits["primitive_normals"].numpy()[keep].astype(np.float64)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals *= -np.sign(np.sum(normals * directions, axis=1, keepdims=True))  # face the camera
    return points, normals, ids[keep]


def best_of(repeats: int, fn):
    """Fastest of ``repeats`` runs: (wall seconds, CPU seconds of that run, result)."""
    best = (np.inf, np.inf, None)
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        result = fn()
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        if wall < best[0]:
            best = (wall, cpu, result)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--candidates", type=int, default=16384)
    parser.add_argument("--parcels", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=0, help="Open3D threads (0: every core)")
    parser.add_argument("--synthetic", action="store_true")
    args = parser.parse_args()

    rng = np.random.default_rng(args.seed)
    meshes, coms, obstacles, bin_spec, source, frame = load_pile(args.parcels, args.seed, args.synthetic)
    if frame is not None:  # the camera's point cloud (estimated normals, background included)
        K, T, width, height = frame.intrinsics, frame.extrinsics, frame.width, frame.height
        chosen = rng.choice(len(frame.points), size=args.candidates, replace=len(frame.points) < args.candidates)
        points = frame.points[chosen].astype(np.float64)
        normals = frame.normals[chosen].astype(np.float64)
        ids = frame.point_object_ids[chosen].astype(np.int64)
        source += f", Camera {width}x{height} point cloud"
    else:
        K, T = overhead_camera(bin_spec)
        width, height = WIDTH, HEIGHT
        points, normals, ids = visible_candidates(meshes, obstacles, K, T, args.candidates, rng)
        source += f", ray-cast {width}x{height} overhead view"
    n = len(points)
    faces = sum(len(m.faces) for m in meshes)

    config = SuctionConfig(num_threads=args.threads)
    t_init, _, scorer = best_of(1, lambda: SuctionScorer(meshes, coms, obstacles, config))
    scorer.seal(points[:8], normals[:8], ids[:8])  # first query builds the BVHs
    # The bellows cup (docs/cup_seal.md) at its 25 mm lip; contact tips hover 1 mm off the surface.
    bellows = SuctionScorer(meshes, coms, obstacles, SuctionConfig(num_threads=args.threads, seal_model="bellows",
                                                                   cup_radius=BELLOWS_RADIUS))
    bellows.seal(points[:8], normals[:8], ids[:8])
    tips = points + 0.001 * normals
    # The `physical` definition (labels, the oracle): the cell's 20 mm bellows cup, seated where its face first
    # meets a hull, then seal, hold and tool; unit masses (the cost does not depend on them)
    cell = SuctionScorer(meshes, coms, obstacles, dataclasses.replace(EnvConfig().suction, seal_model="bellows",
                                                                      num_threads=args.threads),
                         masses=np.ones(len(meshes)))
    cell.physical(points[:8], normals[:8], ids[:8])
    rows = [
        ("seal (72 rim + 19 inner rays)", lambda: scorer.seal(points, normals, ids)),
        ("seal, bellows r=25 mm (91 rays, rim plane fit)", lambda: bellows.seal(points, normals, ids)),
        ("contact_seal, bellows r=25 mm (tips 1 mm off)", lambda: bellows.contact_seal(tips, -normals, ids)),
        ("physical: face seat, bellows r=20 mm, hold, tool", lambda: cell.physical(points, normals, ids)),
        ("wrench", lambda: scorer.wrench(points, normals, ids)),
        ("collision (31 segments)", lambda: scorer.collision(points, normals)),
        ("score: all four + product", lambda: scorer.score(points, normals, ids, visibility)),
        ("nearest_object", lambda: scorer.nearest_object(points)),
    ]
    t_vis, c_vis, visibility = best_of(args.repeats,
                                       lambda: object_visibility(meshes, K, T, width, height, obstacles,
                                                                         num_threads=args.threads))
    results = {name: best_of(args.repeats, fn) for name, fn in rows}
    outputs = [result for _, _, result in results.values()]
    seal, bellows_seal, contact, _, _, coll, scores = outputs[:7]

    print(f"\nScene: {source}, {len(meshes)} parcels, {faces} parcel triangles; "
          f"{n} visible candidates; Open3D {o3d.__version__}, "
          f"{args.threads or 'all'} threads; best of {args.repeats}\n")
    print("| step | wall (ms) | CPU (ms) | candidates/s (wall) |")
    print("|---|---:|---:|---:|")
    for name, (wall, cpu, _) in results.items():
        print(f"| {name} | {wall * 1e3:.1f} | {cpu * 1e3:.1f} | {n / wall:,.0f} |")
    print(f"| object_visibility, {width}x{height} (once per scene) | {t_vis * 1e3:.1f} | {c_vis * 1e3:.1f} | - |")
    print(f"| SuctionScorer.__init__ (once per scene) | {t_init * 1e3:.1f} | - | - |")
    on_parcel = ids >= 0
    reasons = ", ".join(f"{name} {np.mean(contact.reason[on_parcel] == i):.2f}"
                        for i, name in enumerate(contact.REASONS))
    print(f"\nbellows: mean seal {bellows_seal.mean():.3f}; contact_seal mean {contact.quality.mean():.3f}; "
          f"reasons over the {on_parcel.mean():.0%} of candidates on a parcel: {reasons}")
    print(f"mean seal {seal.mean():.3f}, collision-free {coll.mean():.3f}, "
          f"mean total {scores.total.mean():.3f}, mean visibility {visibility.mean():.3f}")
    print(f"peak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
