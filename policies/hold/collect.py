"""Rehearsal-labelled picks: a camera policy's top candidates in closed-loop states, each rehearsed on the cell's twin.

    python -m policies.hold.collect --out data/hold --episodes 30 --seed 1000 --workers 2

Each episode is a closed-loop run of the tool-checked ``--policy`` (default Diffusion-Suction) on a stacked pile,
as ``eval/clearance.py`` runs it, but with its own seeds (``--seed``; the report's grid uses 0). In every state
its first ``--candidates`` passing picks are rehearsed on the twin (``CellTwin.rehearse``: the env's whole
attempt, dynamics and all, from the true pile), and the env then makes the policy's own pick. The twin reads the
privileged state: this is label generation, like the labels' physics, never a policy input. One ``.npz`` per
episode (no pickles): the observed cloud, the candidates, their policy scores and the twin's verdicts.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from eval.clearance import ClearanceConfig, EpisodeTask, episode_env_kwargs, episode_policy, episode_tasks
from parcelpick_env.assets.library import OBJECT_SETS
from parcelpick_env.parallel import BACKENDS, parallel_map
from policies.hold.policy import RERANK


@dataclass(frozen=True)
class CollectTask:
    episode: EpisodeTask
    out: str
    candidates: int


def rehearsal_candidates(passed: np.ndarray, retried: np.ndarray, k: int) -> np.ndarray:
    """Rows of the tool-checked ranking to rehearse: its first ``k`` picks that pass and that the retry rule does
    not pass over (those the cell would take; ``ToolCheckedPolicy.last_passed`` and ``last_retried``)."""
    return np.flatnonzero(np.asarray(passed, dtype=bool) & ~np.asarray(retried, dtype=bool))[:k]


def collect_episode(task: CollectTask) -> dict[str, Any]:
    """One episode's states and rehearsals, written to ``task.out``; returns counts. Top-level for process pools."""
    import gymnasium as gym

    import parcelpick_env  # noqa: F401  (registers ParcelPick-v0)
    from parcelpick_env.assets.library import AssetLibrary
    from policies.cell_twin import CellTwin
    from policies.tool_check import ToolCheckedPolicy

    ep = task.episode
    cfg = ep.config
    policy = episode_policy(cfg)  # as eval/clearance.py acts: through the tool check, with cfg's retry radius
    if not isinstance(policy, ToolCheckedPolicy):
        raise ValueError(f"collect rehearses the tool check's passing picks, which policy {cfg.policy!r} does not go "
                         "through (its own act, or no depth image)")
    env = gym.make("ParcelPick-v0", **episode_env_kwargs(ep), obs_mode="pointcloud")
    unwrapped = env.unwrapped
    twin = CellTwin(unwrapped.config)
    library = AssetLibrary.default(unwrapped.config.asset_seed)
    k = task.candidates
    rows: dict[str, list[np.ndarray]] = {name: [] for name in (
        "points", "normals", "workspace", "cand_points", "cand_normals", "cand_scores", "cand_rank", "twin_outcome",
        "twin_condition", "twin_peak", "env_outcome")}
    try:
        obs, info = env.reset(seed=ep.seed)
        policy.reset(ep.seed)
        while info.get("reason") != "cleared":
            ranked = policy.predict(obs, info, top_k=50)
            if len(ranked) == 0:
                break
            passing = rehearsal_candidates(policy.last_passed, policy.last_retried, k)
            twin.sync(unwrapped.privileged_state(), library)
            outcome = np.full(k, "", dtype="<U16")
            condition = np.full(k, "", dtype="<U32")
            peak = np.full(k, np.nan, dtype=np.float32)
            for j, c in enumerate(passing):
                result = twin.rehearse(ranked.points[c].astype(np.float64), ranked.normals[c].astype(np.float64))
                outcome[j] = result.outcome
                condition[j] = result.failure_cause or ""
                peak[j] = max(result.peak_ratios.values(), default=np.nan)
            pad = k - len(passing)
            rows["points"].append(np.asarray(obs["points"], dtype=np.float32))
            rows["normals"].append(np.asarray(obs["normals"], dtype=np.float32))
            rows["workspace"].append(np.asarray(info["workspace"], dtype=np.float32).reshape(2, 3))
            rows["cand_points"].append(np.pad(ranked.points[passing], ((0, pad), (0, 0)), constant_values=np.nan))
            rows["cand_normals"].append(np.pad(ranked.normals[passing], ((0, pad), (0, 0)), constant_values=np.nan))
            rows["cand_scores"].append(np.pad(ranked.scores[passing], (0, pad), constant_values=np.nan))
            rows["cand_rank"].append(np.pad(passing, (0, pad), constant_values=-1))
            rows["twin_outcome"].append(outcome)
            rows["twin_condition"].append(condition)
            rows["twin_peak"].append(peak)
            obs, _, terminated, truncated, info = env.step(ranked.best_action())
            rows["env_outcome"].append(np.array(info["outcome"], dtype="<U16"))
            if terminated or truncated:
                break
    finally:
        twin.close()
        env.close()
    path = Path(task.out) / f"{ep.objects}-{ep.layout}-ep{ep.episode:03d}.npz"
    arrays = {name: np.stack(v) for name, v in rows.items() if v}
    np.savez_compressed(path, seed=np.int64(ep.seed), **arrays)
    outcomes = arrays.get("twin_outcome", np.zeros((0, k), dtype="<U16"))
    return {"states": int(len(rows["env_outcome"])), "rehearsed": int((outcomes != "").sum()),
            "held": int((outcomes == "success").sum())}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", required=True, help="folder for one .npz per episode")
    p.add_argument("--policy", default="diffusion")
    p.add_argument("--objects", nargs="+", default=list(OBJECT_SETS), choices=OBJECT_SETS)
    p.add_argument("--episodes", type=int, default=10, help="episodes per object set (stacked piles)")
    p.add_argument("--parcels", type=int, default=10)
    p.add_argument("--candidates", type=int, default=RERANK, help="passing picks rehearsed per state")
    p.add_argument("--retry-radius", type=float, default=0.0, metavar="M",
                   help="the cell's retry rule in the tool check, as eval/clearance.py's; 0 is off, as the shipped "
                        "hold check's data were collected (policies/hold/checkpoints/hold.pt records the command)")
    p.add_argument("--seed", type=int, default=1000, help="grid seed; the report's episodes use 0")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--backend", default="local", choices=BACKENDS)
    args = p.parse_args(argv)
    if args.candidates < 1:
        print(f"error: --candidates must be >= 1, got {args.candidates}", file=sys.stderr)
        return 2
    try:
        config = ClearanceConfig(policy=args.policy, objects=tuple(args.objects), layouts=("stacked",),
                                 episodes=args.episodes, num_parcels=args.parcels, seed=args.seed,
                                 workers=args.workers, backend=args.backend, retry_radius=args.retry_radius)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tasks = [CollectTask(t, str(out), args.candidates) for t in episode_tasks(config)]
    counts = list(parallel_map(collect_episode, tasks, workers=args.workers, backend=args.backend,
                               desc="rehearsing", progress=True))
    states = sum(c["states"] for c in counts)
    rehearsed = sum(c["rehearsed"] for c in counts)
    held = sum(c["held"] for c in counts)
    print(f"{len(tasks)} episodes, {states} states, {rehearsed} rehearsals, {held} held on the twin -> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
