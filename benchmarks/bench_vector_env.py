"""Pick attempts per second of ParcelPick-v0 in gymnasium's AsyncVectorEnv with 1 and 2 worker processes.

Each worker process owns one env and its own EGL renderer (``parcelpick_env/sim/egl.py``). The
scripted top-patch picker (a few KD-tree queries, cheap beside the env) chooses every action;
``autoreset_mode=SAME_STEP`` resets a finished episode inside the step that ended it, so every
vector step is one attempt per env and pile builds count against the rate, as they do in training.
Each worker bounds its native thread pools (Open3D's oneTBB and OpenMP, ``--worker-threads``, by
``parcelpick_env.parallel.limit_worker_threads``), so N workers use N cores rather than fighting over them. Prints one markdown table row per worker count (with the
workers' CPU seconds per attempt, which other load on the machine does not inflate), and the speed-up,
beside the lockstep ceiling: what N envs that each wait for the slowest at every step would reach on N free
cores, from the 1-env run's attempt times (``lockstep_ceiling``).

    python benchmarks/bench_vector_env.py --envs 1 2 --seconds 60
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _worker_env(env, threads: int):
    """Runs in the worker process as gymnasium builds its env there: bound its thread pools, drop step infos."""
    from parcelpick_env.parallel import limit_worker_threads

    limit_worker_threads(threads)
    return _without_info(env)


def _without_info(env):
    """Step infos are not needed here, and gymnasium's vector info merge rejects a key that is None in one env
    and a dict in another (``info['failure']`` today), so they are dropped before the merge."""
    import gymnasium as gym

    class WithoutInfo(gym.Wrapper):
        def step(self, action):
            obs, reward, terminated, truncated, _ = self.env.step(action)
            return obs, reward, terminated, truncated, {}

        def reset(self, **kwargs):
            return self.env.reset(**kwargs)[0], {}

    return WithoutInfo(env)


def _actions(obs: dict[str, np.ndarray], n: int) -> np.ndarray:
    from parcelpick_env.envs.scripted import top_patch_action

    return np.stack([top_patch_action({k: obs[k][i] for k in ("points", "normals")}) for i in range(n)])


def lockstep_ceiling(step_times: np.ndarray, n: int) -> float:
    """The speed-up that ``n`` lockstepped envs reach over one when they run in perfect parallel: ``n E[T] / E[max
    of n draws of T]``, ``T`` one env's step time, exactly over the empirical distribution of ``step_times``. A
    vector env's step waits for its slowest env, so the spread of attempt times caps the speed-up below ``n``
    whatever the cores."""
    t = np.sort(np.asarray(step_times, dtype=np.float64))
    below = np.arange(len(t) + 1) / len(t)  # P(T <= t_(k)) for k = 0..m
    expected_max = float(np.sum(t * np.diff(below**n)))
    return n * float(t.mean()) / expected_max


def attempts_per_second(n_envs: int, seconds: float, seed: int, env_kwargs: dict, context: str,
                        worker_threads: int = 1) -> dict:
    """Run ``n_envs`` async envs for about ``seconds`` of stepping (after the first reset)."""
    import gymnasium as gym

    import parcelpick_env  # noqa: F401  (registers ParcelPick-v0)

    cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    parent_before = resource.getrusage(resource.RUSAGE_SELF)
    envs = gym.make_vec("ParcelPick-v0", num_envs=n_envs, vectorization_mode="async",
                        vector_kwargs={"context": context, "autoreset_mode": gym.vector.AutoresetMode.SAME_STEP},
                        wrappers=[partial(_worker_env, threads=worker_threads)], **env_kwargs)
    try:
        started = time.perf_counter()
        obs, _ = envs.reset(seed=seed)
        first_reset = time.perf_counter() - started
        steps, episodes, successes, step_times = 0, 0, 0, []
        started = time.perf_counter()
        while time.perf_counter() - started < seconds:
            t0 = time.perf_counter()
            obs, reward, terminated, truncated, _ = envs.step(_actions(obs, n_envs))
            step_times.append(time.perf_counter() - t0)
            steps += 1
            successes += int(np.sum(reward > 0))
            episodes += int(np.sum(terminated | truncated))
        wall = time.perf_counter() - started
    finally:
        envs.close()  # joins the workers, so their CPU time is counted below (spawn: they are our children)
    cpu_after = resource.getrusage(resource.RUSAGE_CHILDREN)
    parent_after = resource.getrusage(resource.RUSAGE_SELF)
    parent = (parent_after.ru_utime + parent_after.ru_stime) - (parent_before.ru_utime + parent_before.ru_stime)
    cpu = (cpu_after.ru_utime + cpu_after.ru_stime) - (cpu_before.ru_utime + cpu_before.ru_stime)
    attempts = steps * n_envs
    return {"envs": n_envs, "attempts": attempts, "wall": wall, "rate": attempts / wall, "episodes": episodes,
            "successes": successes, "first_reset": first_reset, "cpu_per_attempt": cpu / max(attempts, 1),
            "parent_cpu_per_attempt": parent / max(attempts, 1), "step_times": np.asarray(step_times)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, nargs="+", default=[1, 2], help="worker counts to measure")
    ap.add_argument("--seconds", type=float, default=60.0, help="stepping time per worker count")
    ap.add_argument("--parcels", type=int, default=6)
    ap.add_argument("--layout", default="scattered")
    ap.add_argument("--objects", default="mixed")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--points", type=int, default=4096)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--context", default="spawn", choices=("fork", "forkserver", "spawn"),
                    help="worker start method (spawn: workers are children, so their CPU time is measured)")
    ap.add_argument("--worker-threads", type=int, default=1,
                    help="native threads per worker (Open3D's oneTBB and OpenMP pools)")
    args = ap.parse_args(argv)
    if min(args.envs) < 1 or args.seconds <= 0 or args.worker_threads < 1:
        ap.error("--envs and --worker-threads must be >= 1 and --seconds > 0")
    # OpenMP reads this when a worker first imports Open3D, which gymnasium does before applying the wrappers.
    os.environ["OMP_NUM_THREADS"] = str(args.worker_threads)

    from parcelpick_env.camera.config import CameraConfig

    env_kwargs = dict(num_parcels=args.parcels, layout=args.layout, object_set=args.objects, num_points=args.points,
                      camera=CameraConfig(width=args.width, height=args.height))
    print(f"# ParcelPick-v0 AsyncVectorEnv ({args.context}), {args.parcels} {args.objects} {args.layout} parcels, "
          f"{args.width}x{args.height}, {args.points} points, {os.cpu_count()} CPUs, "
          f"load average before {os.getloadavg()[0]:.2f}")
    print("| envs | attempts | wall s | attempts/s | worker CPU s/attempt | parent CPU s/attempt | episodes | successes | first reset s |")
    print("|---|---|---|---|---|---|---|---|---|")
    rates, single = {}, None
    for n in args.envs:
        r = attempts_per_second(n, args.seconds, args.seed, env_kwargs, args.context, args.worker_threads)
        rates[n] = r["rate"]
        single = r["step_times"] if n == 1 else single
        print(f"| {n} | {r['attempts']} | {r['wall']:.1f} | {r['rate']:.2f} | {r['cpu_per_attempt']:.2f} | {r['parent_cpu_per_attempt']:.3f} | "
              f"{r['episodes']} | {r['successes']} | "
              f"{r['first_reset']:.1f} |", flush=True)
    base = rates.get(1)
    if base:
        for n, rate in rates.items():
            if n != 1:
                print(f"speed-up at {n} envs: {rate / base:.2f}x (lockstep ceiling from the 1-env attempt times: "
                      f"{lockstep_ceiling(single, n):.2f}x)")
    print(f"load average after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
