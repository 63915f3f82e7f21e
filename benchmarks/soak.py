"""Soak test: many resets and attempts across vector envs and the Ray backend, and injected worker crashes.

    python benchmarks/soak.py                                   # the full soak: 500 resets, 2,000 attempts
    python benchmarks/soak.py --resets 40 --attempts 160 --episodes 4 --scenes 4      # a short run

Not part of the test suite (minutes to hours). Four parts, each reported as one JSON line and a summary:

- ``vector``: ``--envs`` ParcelPick-v0 envs in a gymnasium ``AsyncVectorEnv`` (one process each), stepped with
  the scripted top-patch picker until ``--resets`` resets and ``--attempts`` attempts are done. Reports the
  outcome counts, exceptions, and the resident memory (parent plus env processes) after warm-up and at the end.
- ``ray-clearance``: ``--episodes`` clearance episodes (random policy) on the Ray backend, repeated
  ``--rounds`` times in one Ray session; RSS of the driver and workers per round, and failures.
- ``crash-clearance`` / ``crash-dataset``: the same clearance episodes, and a ``--scenes`` dataset, on Ray
  while the first try of every other task kills its worker process (``os._exit``). Ray retries the task,
  and the results must equal an undisturbed local run (episode results; every stored array).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

from parcelpick_env.camera.config import CameraConfig  # noqa: E402

CAMERA = CameraConfig(width=160, height=120)
CRASH_EXIT = 17  # a worker's exit status when the soak kills it on purpose


def rss_mb(process: psutil.Process) -> float:
    """Resident memory of ``process`` and all its descendants, MB."""
    total = 0
    for p in [process, *process.children(recursive=True)]:
        try:
            total += p.memory_info().rss
        except psutil.Error:  # exited meanwhile
            pass
    return total / 1e6


# ------------------------------------------------------------------------------------------------ vector envs

# ParcelPick-v0's info has fields that are None on some steps and an int, float or array on others (e.g.
# failure.body, seal, contact_point): gymnasium's vector info merge then raises TypeError. Until the env
# fills them with typed placeholders, the vector soak keeps only these always-typed fields.
VECTOR_INFO_KEYS = ("outcome", "attempts", "successes", "parcels_cleared", "parcels_placed")


def _make_env(seed: int):
    import parcelpick_env  # noqa: F401  (registers ParcelPick-v0)

    env = gym.make("ParcelPick-v0", num_parcels=3, layout="scattered", object_set="mixed", camera=CAMERA,
                   num_points=1024, max_attempts=4)
    env = TypedInfo(env)
    env.reset(seed=seed)
    return env


def _typed(info: dict[str, Any]) -> dict[str, Any]:
    return {k: info[k] for k in VECTOR_INFO_KEYS if k in info}


class TypedInfo(gym.Wrapper):
    """Returns only ``VECTOR_INFO_KEYS`` of the env's info from ``reset`` and ``step`` (see above)."""

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return obs, _typed(info)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, _typed(info)


def soak_vector(envs: int, resets: int, attempts: int, seed: int) -> dict[str, Any]:
    from functools import partial

    from gymnasium.vector import AsyncVectorEnv

    from parcelpick_env.envs.scripted import top_patch_action

    me = psutil.Process()
    vec = AsyncVectorEnv([partial(_make_env, seed + i) for i in range(envs)], context="spawn")  # EGL: no fork
    outcomes: Counter[str] = Counter()
    errors: list[str] = []
    done_resets, done_attempts, steps = envs, 0, 0
    started = time.perf_counter()
    try:
        obs, _ = vec.reset(seed=seed)
        rss_start = None
        while done_resets < resets or done_attempts < attempts:
            actions = np.stack([top_patch_action({k: v[i] for k, v in obs.items()}) for i in range(envs)])
            try:
                obs, _, terminated, truncated, info = vec.step(actions)
            except Exception as exc:  # noqa: BLE001  a soak counts failures instead of stopping at the first
                errors.append(f"{type(exc).__name__}: {exc}")
                break
            steps += 1
            mask = info.get("_outcome", np.zeros(envs, bool))
            outcomes.update(str(o) for o, m in zip(info.get("outcome", [""] * envs), mask) if m)
            done_attempts += int(np.sum(mask))
            done_resets += int(np.sum(terminated | truncated))  # NEXT_STEP autoreset: the next step resets
            if rss_start is None and steps == 5:
                rss_start = rss_mb(me)  # after warm-up (imports, first piles, renderer buffers)
            if steps % 10 == 0:
                print(f"vector: {done_resets} resets, {done_attempts} attempts, {rss_mb(me):.0f} MB, "
                      f"{time.perf_counter() - started:.0f} s", file=sys.stderr, flush=True)
        rss_end = rss_mb(me)
    except Exception as exc:  # noqa: BLE001
        print(f"vector soak stopped: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
        raise
    finally:
        vec.close(terminate=True)  # a worker still busy must not block the report
    return {"part": "vector", "envs": envs, "resets": done_resets, "attempts": done_attempts, "steps": steps,
            "outcomes": dict(outcomes), "exceptions": errors, "rss_after_warmup_mb": rss_start,
            "rss_end_mb": rss_end, "rss_growth_mb": None if rss_start is None else rss_end - rss_start,
            "seconds": time.perf_counter() - started}


# ------------------------------------------------------------------------------------------------ Ray

def _clearance_config(episodes: int, workers: int, backend: str, seed: int):
    from eval.clearance import ClearanceConfig

    return ClearanceConfig(policy="random", objects=("rectangular", "mixed"), layouts=("scattered",),
                           episodes=max(1, episodes // 2), num_parcels=3, seed=seed, workers=workers,
                           backend=backend, max_attempts=4, env_kwargs={"camera": CAMERA, "num_points": 1024})


def _comparable(episode: dict[str, Any]) -> dict[str, Any]:
    """An episode result without its timings, which no two runs share."""
    out = {k: v for k, v in episode.items() if k != "wall_time_s"}
    out["attempt_log"] = [{k: v for k, v in a.items() if "time" not in k and "seconds" not in k}
                          for a in episode.get("attempt_log", [])]
    return out


def _crashing_episode(args: tuple[Any, str]):
    from eval.clearance import run_episode

    task, marker_dir = args
    if task.index % 2 == 0:
        marker = Path(marker_dir) / f"episode-{task.index}"
        if not marker.exists():
            marker.touch()
            os._exit(CRASH_EXIT)
    return run_episode(task)


def _crashing_annotate(scene_seed: int, config):
    from dataset.annotate import annotate_scene_timed

    marker_dir = os.environ["PARCELPICK_SOAK_MARKERS"]
    if scene_seed % 2 == 0:
        marker = Path(marker_dir) / f"scene-{scene_seed}"
        if not marker.exists():
            marker.touch()
            os._exit(CRASH_EXIT)
    return annotate_scene_timed(scene_seed, config)


def soak_ray_clearance(episodes: int, rounds: int, workers: int, seed: int) -> dict[str, Any]:
    import ray

    from eval.clearance import episode_tasks, run_episode
    from parcelpick_env.parallel import init_ray, parallel_map

    init_ray(None, num_cpus=workers)
    me = psutil.Process()
    config = _clearance_config(episodes, workers, "ray", seed)
    per_round, failures, attempts = [], Counter(), 0
    started = time.perf_counter()
    try:
        for _ in range(rounds):
            for result in parallel_map(run_episode, episode_tasks(config), workers=workers, backend="ray",
                                       progress=False):
                attempts += result.attempts
                failures.update({k: v for k, v in result.outcomes.items() if k != "success"})
            per_round.append(rss_mb(me))
    finally:
        ray.shutdown()
    return {"part": "ray-clearance", "rounds": rounds, "episodes_per_round": len(episode_tasks(config)),
            "attempts": attempts, "failed_attempts_by_outcome": dict(failures), "rss_per_round_mb": per_round,
            "rss_growth_mb": per_round[-1] - per_round[0], "seconds": time.perf_counter() - started}


def soak_crash_clearance(episodes: int, workers: int, seed: int) -> dict[str, Any]:
    import ray

    from eval.clearance import episode_tasks, run_episode
    from parcelpick_env.parallel import init_ray, parallel_map

    config = _clearance_config(episodes, 1, "local", seed)
    tasks = episode_tasks(config)
    reference = [_comparable(dataclasses.asdict(run_episode(t))) for t in tasks]
    markers = tempfile.mkdtemp(prefix="parcelpick_soak_")
    init_ray(None, num_cpus=workers)
    try:
        crashed = [_comparable(dataclasses.asdict(r)) for r in
                   parallel_map(_crashing_episode, [(t, markers) for t in tasks], workers=workers, backend="ray",
                                progress=False)]
    finally:
        ray.shutdown()
    kills = len(os.listdir(markers))
    shutil.rmtree(markers, ignore_errors=True)
    return {"part": "crash-clearance", "episodes": len(tasks), "workers_killed": kills,
            "identical_to_undisturbed": crashed == reference}


def soak_crash_dataset(scenes: int, workers: int, seed: int) -> dict[str, Any]:
    from dataset.config import GenerationConfig
    from dataset.generate import generate
    from dataset.storage import open_dataset

    config = GenerationConfig(scenes=scenes, split="test", seed=seed, min_parcels=2, max_parcels=3, width=160,
                              height=120, annotation_points=512, scenes_per_shard=2, object_set="mixed")
    root = Path(tempfile.mkdtemp(prefix="parcelpick_soak_data_"))
    markers = root / "markers"
    markers.mkdir()
    os.environ["PARCELPICK_SOAK_MARKERS"] = str(markers)  # Ray workers inherit the driver's environment
    try:
        generate(root / "undisturbed", config, progress=False)
        generate(root / "crashed", config, backend="ray", workers=workers, annotate_fn=_crashing_annotate,
                 progress=False)
        a, b = open_dataset(root / "undisturbed"), open_dataset(root / "crashed")
        same = len(a) == len(b) and all(
            sorted(x := a.scene(i)) == sorted(y := b.scene(i)) and all(np.array_equal(x[k], y[k]) for k in x)
            for i in range(len(a)))
        kills = len(os.listdir(markers))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return {"part": "crash-dataset", "scenes": scenes, "workers_killed": kills, "identical_to_undisturbed": same}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python benchmarks/soak.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--resets", type=int, default=500)
    p.add_argument("--attempts", type=int, default=2000)
    p.add_argument("--envs", type=int, default=2, help="AsyncVectorEnv size")
    p.add_argument("--episodes", type=int, default=8, help="clearance episodes per Ray round")
    p.add_argument("--rounds", type=int, default=5, help="Ray clearance rounds (RSS is sampled after each)")
    p.add_argument("--scenes", type=int, default=8, help="scenes of the crash-injected Ray dataset run")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--parts", nargs="+", default=["vector", "ray-clearance", "crash-clearance", "crash-dataset"],
                   choices=["vector", "ray-clearance", "crash-clearance", "crash-dataset"])
    args = p.parse_args(argv)
    runs = {"vector": lambda: soak_vector(args.envs, args.resets, args.attempts, args.seed),
            "ray-clearance": lambda: soak_ray_clearance(args.episodes, args.rounds, args.workers, args.seed),
            "crash-clearance": lambda: soak_crash_clearance(args.episodes, args.workers, args.seed),
            "crash-dataset": lambda: soak_crash_dataset(args.scenes, args.workers, args.seed)}
    ok = True
    for part in args.parts:
        result = runs[part]()
        print(json.dumps(result, default=str), flush=True)
        ok &= not result.get("exceptions") and result.get("identical_to_undisturbed", True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
