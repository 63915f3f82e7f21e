"""Cost of the clearance's tool check (policies/tool_check.py) per decision, and what the mesh stride changes.

    .venv/bin/python benchmarks/bench_tool_check.py [--scenes 4] [--parcels 30] [--candidates 50]

Each scene is a ParcelPick-v0 pile (mixed, stacked) seen by the env's 640x480 camera; the candidates are random
points of the observed cloud with their normals (the check's cost does not depend on which policy proposed them).
For each depth-mesh stride: the wall time of one check (mesh, ray scene, probe) and how many verdicts differ from
the finest mesh (stride 1). Then the check with the seal (``ToolCheckConfig(seal=True)``, the default stride): its
time and how many of the candidates whose tool is clear it turns away.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from parcelpick_env.envs.parcel_pick import ParcelPickEnv  # noqa: E402
from policies.tool_check import ToolCheckConfig, check_picks, tool_clear  # noqa: E402

STRIDES = (1, 2, 3, 4, 6)


def fastest(check, repeats: int) -> tuple[float, np.ndarray]:
    """The fastest of ``repeats`` calls of ``check()`` (seconds) and its verdicts."""
    best, verdicts = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        verdicts = check()
        best = min(best, time.perf_counter() - t0)
    return best, verdicts


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--parcels", type=int, default=30)
    ap.add_argument("--candidates", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=3, help="timed checks per scene and stride (the minimum is kept)")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    times: dict[int, list[float]] = {s: [] for s in STRIDES}
    differ = {s: 0 for s in STRIDES}
    blocked, checked = 0, 0
    seal_times: list[float] = []
    unsealed, clear_at_default = 0, 0
    env = ParcelPickEnv(num_parcels=args.parcels, layout="stacked", object_set="mixed")
    try:
        for seed in range(args.scenes):
            obs, info = env.reset(seed=seed)
            pick = rng.choice(len(obs["points"]), size=min(args.candidates, len(obs["points"])), replace=False)
            points, normals = obs["points"][pick], obs["normals"][pick]
            finest = None
            for stride in STRIDES:
                config = ToolCheckConfig(stride=stride)
                best, clear = fastest(lambda: tool_clear(obs, info, points, normals, config), args.repeats)
                times[stride].append(best)
                finest = clear if finest is None else finest
                differ[stride] += int((clear != finest).sum())
            blocked += int((~finest).sum())
            checked += len(finest)
            with_seal = ToolCheckConfig(seal=True)
            best, passed = fastest(lambda: check_picks(obs, info, points, normals, with_seal), args.repeats)
            seal_times.append(best)
            clear = tool_clear(obs, info, points, normals, with_seal)
            clear_at_default += int(clear.sum())
            unsealed += int((clear & ~passed).sum())
    finally:
        env.close()
    print(f"\nTool check, {args.scenes} piles of {args.parcels} (mixed, stacked), {args.candidates} candidates each, "
          f"640x480 depth; {blocked} of {checked} candidates blocked at stride 1\n")
    print("| stride (px) | check, median ms | check, max ms | verdicts differing from stride 1 |")
    print("|---|---|---|---|")
    for stride in STRIDES:
        t = 1000 * np.asarray(times[stride])
        print(f"| {stride} | {np.median(t):.1f} | {t.max():.1f} | {differ[stride]} of {checked} |")
    t = 1000 * np.asarray(seal_times)
    print(f"\nWith the seal (stride {ToolCheckConfig().stride}): median {np.median(t):.1f} ms, max {t.max():.1f} ms; "
          f"it turns away {unsealed} of the {clear_at_default} candidates whose tool is clear")


if __name__ == "__main__":
    main()
