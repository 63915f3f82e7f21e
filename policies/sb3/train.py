"""PPO on ParcelPick-v0 with ``action_mode='pixel'``: a small, honest reinforcement-learning baseline.

The policy sees only a downsampled depth image (``DepthOnly``: block-mean pooled to ``--grid`` cells,
metres divided by the camera's far plane, flattened) and outputs a pixel in [-1, 1]^2; the env turns
it into a suction point (back-projected depth) and normal (the camera's estimate) and runs the
physical pick. Reward is 1 per delivered parcel. Small scenes (3 scattered cartons by default)
keep a step around a few tenths of a second on 2 CPU cores, so a few thousand steps take minutes:

    python -m policies.sb3.train --timesteps 2000 --seed 0

Writes the model as data-only safetensors (``policies.sb3.model_io``; by default the file the ``sb3`` policy
ships with, never a pickled SB3 zip) and a JSON beside it with the episode rewards, and prints the mean
reward of the first and last 10% of episodes.
"""

from __future__ import annotations

import argparse
import json
import time
from functools import partial

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from tqdm import tqdm

import parcelpick_env  # noqa: F401  (registers ParcelPick-v0)
from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.cli import check_output_path, run_cli
from parcelpick_env.parallel import limit_worker_threads
from policies.provenance import command_line, repo_path, training_provenance
from policies.sb3.features import DEFAULT_GRID, depth_features
from policies.sb3.model_io import save_model
from policies.sb3.policy import DEFAULT_MODEL


class DepthOnly(gym.ObservationWrapper):
    """Keep only the depth image, as ``depth_features`` (the same features the SB3 policy computes)."""

    def __init__(self, env: gym.Env, grid: tuple[int, int] = DEFAULT_GRID) -> None:
        super().__init__(env)
        h, w, _ = env.observation_space["depth"].shape
        rows, cols = grid
        if h % rows or w % cols:
            raise ValueError(f"depth {h}x{w} must divide evenly into a {rows}x{cols} grid")
        self.grid = grid
        self.far = float(env.observation_space["depth"].high.max())
        self.observation_space = gym.spaces.Box(0.0, 1.0, (rows * cols,), np.float32)

    def observation(self, obs):
        return depth_features(obs["depth"], self.grid, self.far)


class TqdmCallback(BaseCallback):
    """Progress bar over environment steps (SB3's own bar needs `rich`, which this project does not install)."""

    def __init__(self, total: int) -> None:
        super().__init__()
        self.total = total

    def _on_training_start(self) -> None:
        self.bar = tqdm(total=self.total, desc="PPO", unit="step")

    def _on_step(self) -> bool:
        self.bar.update(self.training_env.num_envs)  # one call per vector step
        return True

    def _on_training_end(self) -> None:
        self.bar.close()


def make_env(seed: int, num_parcels: int = 3, layout: str = "scattered", object_set: str = "rectangular") -> gym.Env:
    env = gym.make("ParcelPick-v0", action_mode="pixel", num_parcels=num_parcels, layout=layout,
                   object_set=object_set, camera=CameraConfig(width=160, height=120), num_points=256,
                   max_attempts=2 * num_parcels + 2)
    env = DepthOnly(env)
    env.reset(seed=seed)
    return env


def _monitored_env(seed: int, num_parcels: int, layout: str, object_set: str, worker: bool = False) -> gym.Env:
    from stable_baselines3.common.monitor import Monitor

    if worker:  # one of several processes on the machine: one core each (parcelpick_env/parallel.py)
        limit_worker_threads()
    return Monitor(make_env(seed, num_parcels, layout, object_set))


def make_vec_env(n_envs: int, seed: int, num_parcels: int = 3, layout: str = "scattered",
                 object_set: str = "rectangular"):
    """``n_envs`` monitored envs: in this process when 1, else one worker process each (SB3's
    SubprocVecEnv; every process owns its own EGL renderer, parcelpick_env/sim/egl.py). PPO seeds env i
    with ``seed + i``."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    fns = [partial(_monitored_env, seed + i, num_parcels, layout, object_set, n_envs > 1) for i in range(n_envs)]
    return DummyVecEnv(fns) if n_envs == 1 else SubprocVecEnv(fns)


def episode_log(venv) -> list[tuple[float, int]]:
    """(reward, length) of every finished episode of every env, in the order they finished."""
    per_env = zip(venv.env_method("get_episode_rewards"), venv.env_method("get_episode_lengths"),
                  venv.env_method("get_episode_times"))
    done = [(t, float(r), int(n)) for rewards, lengths, times in per_env for r, n, t in zip(rewards, lengths, times)]
    return [(r, n) for _, r, n in sorted(done)]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="PPO on ParcelPick-v0 (pixel actions, depth-only observations)")
    ap.add_argument("--timesteps", type=int, default=2000)
    ap.add_argument("--out", default=str(DEFAULT_MODEL), help="model .safetensors (default: the shipped sb3 policy)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--parcels", type=int, default=3)
    ap.add_argument("--layout", default="scattered")
    ap.add_argument("--objects", default="rectangular")
    ap.add_argument("--n-steps", type=int, default=128, help="PPO rollout length")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (the env, not the MLP, is the cost)")
    ap.add_argument("--n-envs", type=int, default=1,
                    help="envs stepped in parallel, one process each (SubprocVecEnv) when > 1; env i is seeded seed + i")
    args = ap.parse_args(argv)
    if args.timesteps < 1 or args.n_steps < 2 or args.threads < 1 or args.n_envs < 1:
        ap.error("--timesteps must be >= 1, --n-steps >= 2, --threads >= 1 and --n-envs >= 1")
    out = check_output_path(args.out, "--out")

    import torch
    from stable_baselines3 import PPO

    torch.set_num_threads(args.threads)
    env = make_vec_env(args.n_envs, args.seed, args.parcels, args.layout, args.objects)
    model = PPO("MlpPolicy", env, n_steps=args.n_steps, batch_size=min(64, args.n_steps), n_epochs=4,
                learning_rate=3e-4, gamma=0.9, seed=args.seed, verbose=0, device="cpu")
    started = time.perf_counter()
    model.learn(total_timesteps=args.timesteps, callback=TqdmCallback(args.timesteps))
    save_model(model.policy, out)
    episodes = episode_log(env)
    rewards = np.array([r for r, _ in episodes], dtype=np.float64)
    tenth = max(1, len(rewards) // 10)
    first = rewards[:tenth].mean() if len(rewards) else float("nan")
    last = rewards[-tenth:].mean() if len(rewards) else float("nan")
    log = {"command_args": dict(vars(args), out=repo_path(out)), "timesteps": args.timesteps,
           "seconds": time.perf_counter() - started,
           "provenance": training_provenance(command_line("policies.sb3.train", argv), args.seed, None, started),
           "episode_rewards": rewards.tolist(), "episode_lengths": [n for _, n in episodes],
           "first_tenth_mean_reward": first, "last_tenth_mean_reward": last}
    out.with_suffix(".json").write_text(json.dumps(log, indent=1))
    print(f"episodes {len(rewards)}, timesteps {args.timesteps}: mean episode reward first 10% {first:.2f}, "
          f"last 10% {last:.2f} -> {out}")
    env.close()


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
