"""Vector envs (gymnasium async/sync, SB3 Subproc/Dummy) reproduce single envs under the same seeds.

gymnasium seeds sub-env ``i`` of ``reset(seed=s)`` with ``s + i``, SB3 does the same after ``seed(s)``;
so sub-env ``i`` must see exactly what a single env reset with ``s + i`` sees, step after step.
Each process owns its EGL renderer (``sim/egl.py``): fork, spawn and forkserver workers all render.
"""

from __future__ import annotations

import multiprocessing as mp
import subprocess
import sys
import textwrap
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import parcelpick_env  # noqa: F401  (registers ParcelPick-v0)
from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.envs.parcel_pick import ParcelPickEnv
from parcelpick_env.envs.scripted import top_patch_action
from parcelpick_env.sim.egl import EGLForkError
from parcelpick_env.sim.simulator import Simulator

KWARGS = dict(num_parcels=2, layout="scattered", object_set="rectangular", num_points=256,
              camera=CameraConfig(width=160, height=120))
SEED, NUM_ENVS, STEPS = 11, 2, 3
KEYS = ("points", "normals", "rgb", "depth")
ROOT = Path(__file__).resolve().parents[1]
SAME_STEP = gym.vector.AutoresetMode.SAME_STEP  # a finished sub-env is reset inside the step, as SB3 does


def _actions(obs: dict[str, np.ndarray]) -> np.ndarray:
    """One scripted pick per sub-env, from that sub-env's own observation."""
    return np.stack([top_patch_action({k: obs[k][i] for k in ("points", "normals")}) for i in range(NUM_ENVS)])


def _stack(per_env: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {k: np.stack([o[k] for o in per_env]) for k in KEYS}


def _step_or_reset(env: ParcelPickEnv, action: np.ndarray) -> dict[str, np.ndarray]:
    """A step; when it ends the episode, the next episode's first observation instead (what SB3's VecEnvs and
    gymnasium's SAME_STEP autoreset return: ``reset()`` without a seed, continuing the env's generator)."""
    obs, _, terminated, truncated, _ = env.step(action)
    return env.reset()[0] if terminated or truncated else obs


@pytest.fixture(scope="module")
def reference() -> list[dict[str, np.ndarray]]:
    """Observations (reset, then each step) of NUM_ENVS single envs seeded SEED + i, stacked per time."""
    envs = [ParcelPickEnv(**KWARGS) for _ in range(NUM_ENVS)]
    try:
        obs = _stack([env.reset(seed=SEED + i)[0] for i, env in enumerate(envs)])
        trace = [obs]
        for _ in range(STEPS):
            actions = _actions(obs)
            obs = _stack([_step_or_reset(env, a) for env, a in zip(envs, actions)])
            trace.append(obs)
        return trace
    finally:
        for env in envs:
            env.close()


def _assert_same(trace: list[dict[str, np.ndarray]], reference: list[dict[str, np.ndarray]]) -> None:
    assert len(trace) == len(reference)
    for t, (got, want) in enumerate(zip(trace, reference)):
        for k in KEYS:
            np.testing.assert_array_equal(got[k], want[k], err_msg=f"{k} at time {t}")


class ObservationsOnly(gym.Wrapper):
    """Drops step and reset infos: these tests compare observations only (infos are exercised by
    ``test_vector_env_steps_through_episode_ends_and_mixed_outcomes``)."""

    def step(self, action):
        obs, reward, terminated, truncated, _ = self.env.step(action)
        return obs, reward, terminated, truncated, {}

    def reset(self, **kwargs):
        return self.env.reset(**kwargs)[0], {}


def _run_gym_vector(env: gym.vector.VectorEnv) -> list[dict[str, np.ndarray]]:
    failed = True
    try:
        obs, _ = env.reset(seed=SEED)
        trace = [{k: np.asarray(obs[k]) for k in KEYS}]
        for _ in range(STEPS):
            obs, *_ = env.step(_actions(obs))
            trace.append({k: np.asarray(obs[k]) for k in KEYS})
        failed = False
        return trace
    finally:
        # After an error inside step_wait, AsyncVectorEnv.close() would wait forever for that step: terminate.
        env.close(**({"terminate": True} if failed and isinstance(env, gym.vector.AsyncVectorEnv) else {}))


def test_reference_is_seed_dependent(reference):
    """Guards the comparisons below: the two sub-envs really see different piles."""
    assert not np.array_equal(reference[0]["points"][0], reference[0]["points"][1])


@pytest.mark.parametrize("mode, context", [("sync", None), ("async", "spawn"), ("async", "forkserver")])
def test_gym_vector_env_matches_single_envs(reference, mode, context):
    vector_kwargs = {"autoreset_mode": SAME_STEP, **({"context": context} if context else {})}
    env = gym.make_vec("ParcelPick-v0", num_envs=NUM_ENVS, vectorization_mode=mode, vector_kwargs=vector_kwargs,
                       wrappers=[ObservationsOnly], **KWARGS)
    _assert_same(_run_gym_vector(env), reference)


def test_default_async_vector_env_forks_and_renders(reference, tmp_path):
    """The issue's hang: make_vec(async) with fork workers, from a fresh process that has built (and so
    far rendered nothing with) the throw-away env gymnasium makes to read the spaces."""
    out = tmp_path / "trace.npz"
    script = textwrap.dedent(f"""
        import numpy as np, gymnasium as gym, parcelpick_env
        from tests.test_vector_env import KWARGS, NUM_ENVS, SAME_STEP, ObservationsOnly, _run_gym_vector
        env = gym.make_vec("ParcelPick-v0", num_envs=NUM_ENVS, vectorization_mode="async",
                           vector_kwargs={{"context": "fork", "autoreset_mode": SAME_STEP}}, wrappers=[ObservationsOnly],
                           **KWARGS)
        trace = _run_gym_vector(env)
        np.savez({str(out)!r}, **{{f"{{t}}/{{k}}": v for t, o in enumerate(trace) for k, v in o.items()}})
    """)
    subprocess.run([sys.executable, "-c", script], check=True, timeout=240, capture_output=True, cwd=ROOT)
    data = np.load(out)
    trace = [{k: data[f"{t}/{k}"] for k in KEYS} for t in range(STEPS + 1)]
    _assert_same(trace, reference)


def _run_sb3(venv) -> list[dict[str, np.ndarray]]:
    try:
        venv.seed(SEED)
        obs = venv.reset()
        trace = [{k: np.asarray(obs[k]) for k in KEYS}]
        for _ in range(STEPS):
            obs, *_ = venv.step(_actions(obs))
            trace.append({k: np.asarray(obs[k]) for k in KEYS})
        return trace
    finally:
        venv.close()


def _make_env() -> gym.Env:
    return gym.make("ParcelPick-v0", **KWARGS)


@pytest.mark.parametrize("kind", ["dummy", "subproc"])
def test_sb3_vec_envs_match_single_envs(reference, kind):
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    cls = DummyVecEnv if kind == "dummy" else SubprocVecEnv  # SubprocVecEnv: forkserver by default
    _assert_same(_run_sb3(cls([_make_env] * NUM_ENVS)), reference)


def _child_renders(queue) -> None:
    try:
        with Simulator() as sim:
            queue.put(("ok", sim.egl_enabled))
    except EGLForkError as exc:
        queue.put(("EGLForkError", str(exc)))


def test_fork_after_parent_rendered_fails_clearly_instead_of_hanging():
    with Simulator() as sim:
        if not sim.egl_enabled:
            pytest.skip("no EGL here: nothing is inherited through fork")
        ctx = mp.get_context("fork")
        queue = ctx.Queue()
        child = ctx.Process(target=_child_renders, args=(queue,))
        child.start()
        child.join(60)
        if child.is_alive():
            child.kill()
            pytest.fail("the forked child hung starting EGL")
        kind, message = queue.get(timeout=5)
    assert kind == "EGLForkError"
    assert "spawn" in message and "forkserver" in message


def test_vector_env_steps_through_episode_ends_and_mixed_outcomes():
    """Sub-env 0 clears its one box (success, episode over, autoreset); sub-env 1 keeps failing."""
    from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox

    box = BoxScene([PlacedBox((0.30, 0.20, 0.10), 0.5)])
    env = gym.make_vec("ParcelPick-v0", num_envs=2, vectorization_mode="sync", scene_factory=box, max_attempts=2,
                       num_points=256, camera=CameraConfig(width=160, height=120))
    top = np.array([0.0, 0.0, box.bin.floor_z + 0.10, 0.0, 0.0, 1.0], np.float32)
    actions = np.stack([top, np.full(6, np.nan, np.float32)])
    try:
        env.reset(seed=0)
        steps = [env.step(actions) for _ in range(3)]
    finally:
        env.close()
    (_, _, term0, trunc0, info0), (_, _, term1, trunc1, _), (_, reward2, _, _, info2) = steps
    assert tuple(info0["outcome"]) == ("success", "invalid_action") and term0.tolist() == [True, False]
    assert trunc1.tolist() == [False, True]  # sub-env 1: its second failed attempt hits max_attempts
    assert reward2[0] == 1.0 and info2["outcome"][0] == "success"  # sub-env 0 was reset and picked again


def test_ppo_trains_on_two_worker_processes(tmp_path):
    """``policies.sb3.train --n-envs 2``: one SubprocVecEnv worker per env; every env step is logged."""
    import json

    from policies.sb3.train import main

    out = tmp_path / "ppo.safetensors"
    main(["--timesteps", "16", "--n-steps", "4", "--parcels", "1", "--n-envs", "2", "--seed", "0", "--out", str(out)])
    log = json.loads(out.with_suffix(".json").read_text())
    assert log["command_args"]["n_envs"] == 2
    assert len(log["episode_rewards"]) >= 2 and sum(log["episode_lengths"]) <= 16  # episodes from both workers
