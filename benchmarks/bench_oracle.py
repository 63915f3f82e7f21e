"""What an oracle decision costs, and how much of it is the cell's own plan and rehearsal on the twin (policies/cell_twin.py).

    .venv/bin/python benchmarks/bench_oracle.py [--parcels 10 30] [--piles 3] [--repeats 3]

Each pile is a stacked mixed ``ParcelPick-v0`` pile (``obs_mode="state_dict"``) built by the env at a fixed seed;
the oracle decides on it ``--repeats`` times (reset between, so nothing is remembered), once more with the twin
answering at once and nothing rehearsed (the rest of the decision's cost), and the twin's parts are timed on their
own: a sync to a pile it does not hold yet, and the plan (``CellTwin.refusal``), lift test (``CellTwin.lifts``,
30 cm up) and rehearsal (``CellTwin.rehearse``, the whole attempt with dynamics) of the pick the oracle chose,
and the list of parting pushes it would try at a dead end (``policies/parting.py``'s ``push_candidates``, up to
``OracleConfig.push_trials``, in the env's action box; the push rehearsals themselves are not timed here). The shadow
of the cell (``policies/shadow_cell.py``, what ``act`` rehearses on by default) is timed too: its start on an
episode's pile (an env reset at a 64 x 48 camera) and its rehearsal of the same pick (a forked child runs the
attempt); following a step of the env costs it one env step (benchmarks/bench_env.py).
Medians over every pile and repeat; a decision rehearses more than once only where its first pick fails there.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gymnasium as gym  # noqa: E402

import parcelpick_env  # noqa: E402,F401  (registers ParcelPick-v0)
from parcelpick_env.assets.library import AssetLibrary  # noqa: E402
from parcelpick_env.camera.config import CameraConfig  # noqa: E402
from parcelpick_env.envs.config import EnvConfig  # noqa: E402
from parcelpick_env.envs.observation import bin_from_vector  # noqa: E402
from policies.cell_twin import CellTwin  # noqa: E402
from policies.oracle import OracleConfig, OraclePolicy, ground_truth, pinned_parcels  # noqa: E402
from policies.parting import push_candidates  # noqa: E402
from policies.shadow_cell import ShadowCell  # noqa: E402


def timed(fn) -> tuple[float, object]:
    start = time.perf_counter()
    out = fn()
    return (time.perf_counter() - start) * 1e3, out


def list_pushes(obs, library, cup_radius: float, limit: int, box) -> list:
    """The oracle's parting pushes on ``obs``'s pile, from its true scene as the oracle reads it at a dead end."""
    truth = ground_truth(obs, library)
    return push_candidates(truth, pinned_parcels(truth), cup_radius, limit, box)


def bench(parcels: int, piles: int, repeats: int) -> dict[str, float]:
    env = gym.make("ParcelPick-v0", object_set="mixed", layout="stacked", num_parcels=parcels,
                   obs_mode="state_dict", camera=CameraConfig(width=160, height=120), num_points=256)
    policy, twin, shadow = OraclePolicy(), CellTwin(), ShadowCell()
    # the same oracle with the twin's answers given at once and no rehearsal: what the rest of a decision costs
    untwinned = OraclePolicy(OracleConfig(rehearsals=0))
    untwinned.twin.refusal = lambda point, normal: None  # type: ignore[method-assign]
    untwinned.twin.lifts = lambda point, normal, top: True  # type: ignore[method-assign]
    rows: dict[str, list[float]] = {"decision": [], "untwinned": [], "sync": [], "plan": [], "lift": [],
                                    "rehearsal": [], "rehearsals": [], "push_list": [], "pushes": [],
                                    "shadow_start": [], "shadow_rehearsal": []}
    try:
        for pile in range(piles):
            obs, info = env.reset(seed=pile)
            library = AssetLibrary.default(int(info["asset_seed"]))
            box = bin_from_vector(obs["bin"]).workspace(margin=EnvConfig().action_margin)  # the env's action box
            cup_radius = info.get("suction", policy.suction).cup_radius
            for _ in range(repeats):
                policy.reset()
                ms, picks = timed(lambda: policy.predict(obs, info))
                rows["decision"].append(ms)
                rows["rehearsals"].append(len(policy.last_rehearsals))
                untwinned.reset()
                rows["untwinned"].append(timed(lambda: untwinned.predict(obs, info))[0])
                fresh = dict(obs)  # a pile the twin does not hold yet
                rows["sync"].append(timed(lambda: twin.sync(fresh, library))[0])
                point, normal = picks.points[0].astype(np.float64), picks.normals[0].astype(np.float64)
                rows["plan"].append(timed(lambda: twin.refusal(point, normal))[0])
                rows["lift"].append(timed(lambda: twin.lifts(point, normal, float(point[2]) + 0.3))[0])
                rows["rehearsal"].append(timed(lambda: twin.rehearse(point, normal))[0])
                shadow.new_episode()
                ms, live = timed(lambda: shadow.track(obs, info))
                if not live:
                    raise RuntimeError(f"the shadow does not follow the env's pile: {shadow.why_not}")
                rows["shadow_start"].append(ms)
                rows["shadow_rehearsal"].append(timed(lambda: shadow.rehearse(point, normal))[0])
                ms, pushes = timed(lambda: list_pushes(obs, library, cup_radius, policy.config.push_trials, box))
                rows["push_list"].append(ms)
                rows["pushes"].append(len(pushes))
    finally:
        twin.close()
        shadow.close()
        env.close()
    return {name: float(np.median(values)) for name, values in rows.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--parcels", type=int, nargs="+", default=[10, 30])
    parser.add_argument("--piles", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    if min(args.parcels) < 1 or args.piles < 1 or args.repeats < 1:
        parser.error("--parcels, --piles and --repeats must be >= 1")
    print(f"stacked mixed piles, {args.piles} piles x {args.repeats} decisions each; medians")
    print("| parcels | oracle decision | rehearsals in it | the same, twin answering at once, no rehearsal | twin sync "
          "(new pile) | cell's plan of the pick | lift test of the pick (30 cm) | rehearsal of the pick | parting pushes "
          "listed (truth, pinning, list) | pushes listed | shadow start (its reset) | shadow rehearsal of the pick (fork) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for parcels in args.parcels:
        r = bench(parcels, args.piles, args.repeats)
        print(f"| {parcels} | {r['decision']:.0f} ms | {r['rehearsals']:.0f} | {r['untwinned']:.0f} ms | "
              f"{r['sync']:.1f} ms | {r['plan']:.0f} ms | {r['lift']:.0f} ms | {r['rehearsal']:.0f} ms | "
              f"{r['push_list']:.0f} ms | {r['pushes']:.0f} | {r['shadow_start']:.0f} ms | {r['shadow_rehearsal']:.0f} ms |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
