"""Inference latency of the non-learned baselines (Normal-STD, random) at the env's 640x480 depth.

    .venv/bin/python benchmarks/bench_policies.py [--repeats 5] [--boxes 12]

The observation is a ray-cast pile of random boxes on a floor seen from 1 m, so the numbers do not
depend on the simulator; the cloud holds every valid pixel (the largest cloud a policy can get).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from policies.heatmap import pixels_to_world  # noqa: E402
from policies.normal_std import NormalStdConfig, NormalStdPolicy  # noqa: E402
from policies.random_policy import RandomPolicy  # noqa: E402


def synthetic_observation(width: int = 640, height: int = 480, boxes: int = 12, seed: int = 0):
    rng = np.random.default_rng(seed)
    scene = o3d.t.geometry.RaycastingScene()
    floor = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 0.01).translate((-1.0, -1.0, -0.01))
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(floor))
    for _ in range(boxes):
        size = rng.uniform(0.05, 0.3, 3)
        box = o3d.geometry.TriangleMesh.create_box(*size).translate(-size / 2)
        box.rotate(o3d.geometry.get_rotation_matrix_from_xyz(rng.uniform(-0.3, 0.3, 3) * [1, 1, 10]))
        box.translate((*rng.uniform(-0.3, 0.3, 2), size[2] / 2 + rng.uniform(0, 0.1)))
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box))
    focal = 0.5 * width / np.tan(np.radians(30))
    K = np.array([[focal, 0, width / 2 - 0.5], [0, focal, height / 2 - 0.5], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = (0.0, 0.0, 1.0)
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(o3d.core.Tensor(K), o3d.core.Tensor(np.linalg.inv(T)),
                                                              width, height)
    t_hit = scene.cast_rays(rays)["t_hit"].numpy()
    depth = np.where(np.isfinite(t_hit), t_hit * (rays.numpy()[..., 3:] @ T[:3, :3])[..., 2], 0).astype(np.float32)
    points = pixels_to_world(*np.nonzero(depth > 0), depth, K, T)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
    cloud.orient_normals_towards_camera_location(T[:3, 3])
    obs = {"depth": depth[..., None], "points": points.astype(np.float32),
           "normals": np.asarray(cloud.normals, dtype=np.float32), "rgb": np.zeros((height, width, 3), np.uint8)}
    return obs, {"intrinsics": K, "extrinsics": T}


def time_policy(policy, obs, info, repeats: int, top_k: int) -> tuple[float, float]:
    policy.predict(obs, info, top_k=top_k)  # warm-up (imports, Open3D thread pool)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        policy.predict(obs, info, top_k=top_k)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) * 1e3, float(np.min(times)) * 1e3


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--boxes", type=int, default=12)
    parser.add_argument("--top-k", type=int, default=50)
    parser.add_argument("--full-res", action="store_true",
                        help="also time Normal-STD at full resolution with KNN 224 (about a minute per call)")
    args = parser.parse_args(argv)
    obs, info = synthetic_observation(boxes=args.boxes)
    rows = [
        ("normal_std (default: downsample 2, KNN 56)", NormalStdPolicy()),
        ("normal_std (downsample 4, KNN 16)", NormalStdPolicy(NormalStdConfig(downsample=4))),
        ("random", RandomPolicy(seed=0)),
    ]
    if args.full_res:
        rows.insert(0, ("normal_std (full res, KNN 224)", NormalStdPolicy(NormalStdConfig(downsample=1))))
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; 640x480 depth, "
          f"{len(obs['points'])} cloud points, top_k={args.top_k}, {args.repeats} repeats\n")
    print("| policy | median ms | min ms |")
    print("|---|---|---|")
    for name, policy in rows:
        median, best = time_policy(policy, obs, info, args.repeats, args.top_k)
        print(f"| {name} | {median:.1f} | {best:.1f} |")
    print(f"\npeak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
