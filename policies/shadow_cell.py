"""A shadow of the pick cell: the env's own code, on the env's pile, with the env's contact history.

The oracle's twin (``policies/cell_twin.py``) is posed from the ``state_dict`` observation, so its contacts start
fresh from float32 poses, and a chaotic lift may end otherwise in the env: on the 30-parcel heap the env failed 41
of the 1,159 picks the twin had held (results/ORACLE.md, 'The shadow of the cell'; on the shadow, 3 of 1,156,
each a float64 pick the env received as float32, which ``rehearse`` now steps as the env will).
The simulator is deterministic (``reset(seed)`` and the same actions give the same episode to the bit), so a
second env, built from the real env's ``EnvConfig`` (``info['env_config']``, in the privileged ``state_dict`` mode
only), reset to the same pile (``info['scene_seed']``) and stepped with every action the real env took, *is* the
real cell's state, contacts and all. ``ShadowCell`` keeps such an env, checks after every step that its parcels lie
exactly where the observation has them, and ``rehearse`` steps a pick on it in a forked child process: what the
env would do with that pick, exactly, while the shadow itself never moves. pybullet's own ``saveState`` and
``restoreState`` are not used because the restore does not give back the same continuation here (measured: the
next step differed from the env's). Where the shadow cannot follow (no ``fork``, a pixel action mode, an
observation it does not match, a child that fails), ``live`` turns False and the oracle rehearses on its twin.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from typing import Any, Callable, Mapping

import numpy as np

from parcelpick_env.envs.config import EnvConfig
from parcelpick_env.envs.grasp import Failure, PickResult
from parcelpick_env.envs.push import pick_action

# the observation entries that must agree to the bit for the shadow to be the env's state, and the info counts
# that must agree for its episode to end where the env's does (an action the env refused moves no parcel)
MATCHED_KEYS: tuple[str, ...] = ("parcel_mask", "parcel_position", "parcel_quaternion")
MATCHED_COUNTS: tuple[str, ...] = ("attempts", "pushes", "consecutive_failures", "parcels_remaining")
SHADOW_CAMERA = (64, 48)  # the shadow renders nothing the oracle reads: a small frame, with TinyRenderer


def shadow_config(config: EnvConfig) -> EnvConfig:
    """The real env's configuration for its shadow: the same cell and physics, no replays, no EGL context (one
    per process is the env's), a small camera (the camera moves nothing), the privileged observation."""
    return dataclasses.replace(
        config, obs_mode="state_dict", record_dir=None,
        sim=dataclasses.replace(config.sim, egl_rendering=False),
        camera=dataclasses.replace(config.camera, width=SHADOW_CAMERA[0], height=SHADOW_CAMERA[1], renderer="tiny"))


class ShadowCell:
    """A private ParcelPick env that follows the real one: ``track`` once per decision, ``expect`` the action
    taken, ``rehearse`` a pick (exact) while ``live``."""

    def __init__(self) -> None:
        self.env: Any = None  # the shadow ParcelPickEnv, made on the first episode
        self._config: EnvConfig | None = None
        self._pending: np.ndarray | None = None  # the action the real env took since the last track
        self._info: Mapping[str, Any] = {}  # the shadow's own info after its last reset or step
        self._started = False  # reset to this episode's pile
        self.live = False  # the shadow is the real env's state (checked at the last track)
        self.why_not: str | None = None  # why it is not live, once it stopped following

    def new_episode(self) -> None:
        """Forget the last episode: the next ``track`` builds this one's pile."""
        self._pending, self._started, self.live, self.why_not, self._info = None, False, False, None, {}

    def expect(self, action: np.ndarray) -> None:
        """The action about to be sent to the real env (followed at the next ``track``)."""
        self._pending = np.array(action, dtype=np.float32, copy=True)

    def track(self, obs: Mapping[str, Any], info: Mapping[str, Any]) -> bool:
        """Bring the shadow to the real env's state: at an episode's first decision, its pile; later, the step
        the real env took. Then ``live`` is whether its parcels lie exactly where ``obs`` has them."""
        if self.why_not is not None:
            return False
        try:
            if not self._started:
                self._start(info)
            elif self._pending is not None:
                self._info = self.env.step(self._pending)[4]
            self._pending = None
            self.live = self._matches(obs, info)
            if not self.live:
                self.why_not = "its parcels or counts differ from the observation's"
        except _CannotFollow as exc:
            self.live, self.why_not = False, str(exc)
        except Exception as exc:  # noqa: BLE001 - a shadow that breaks leaves the oracle its twin, not a crash
            self.live, self.why_not = False, f"its env failed: {type(exc).__name__}: {exc}"
        return self.live

    def _start(self, info: Mapping[str, Any]) -> None:
        config, scene_seed = info.get("env_config"), info.get("scene_seed")
        if not isinstance(config, EnvConfig) or scene_seed is None:
            raise _CannotFollow("no env_config and scene_seed in info (obs_mode='state_dict' gives them)")
        if config.action_mode == "pixel":
            raise _CannotFollow("pixel actions map through the env's own camera frame")
        if not hasattr(os, "fork"):
            raise _CannotFollow("this platform has no fork for the rehearsals")
        if config != self._config:
            self.close()
            from parcelpick_env.envs.parcel_pick import ParcelPickEnv

            self.env, self._config = ParcelPickEnv(shadow_config(config)), config
        self._info = self.env.reset(options={"scene_seed": int(scene_seed)})[1]
        self._started = True

    def _matches(self, obs: Mapping[str, Any], info: Mapping[str, Any]) -> bool:
        if not all(k in obs for k in MATCHED_KEYS) or any(info.get(k) != self._info.get(k) for k in MATCHED_COUNTS):
            return False
        mine = self.env.unwrapped.privileged_state()
        return all(np.array_equal(np.asarray(mine[k]), np.asarray(obs[k])) for k in MATCHED_KEYS)

    def rehearse(self, point: np.ndarray, normal: np.ndarray) -> tuple[PickResult, int] | None:
        """The pick as the env would run it now: the action it would receive (float32, as every policy's action
        reaches it; rounding a float64 pick to float32 has turned a held rehearsal into a drop), stepped on a forked
        copy of the shadow: that step's ``PickResult``, and how many parcels it knocked out of the tote (the env's
        ``parcels_lost``, which R_object charges). None where the child failed (then the shadow stops being used
        this episode)."""
        if self._config is None:
            return None
        action = pick_action(np.concatenate([point, normal]), self._config.action_mode)
        answer = self.foresee(functools.partial(_attempt, action=action))
        if answer is None:
            return None
        failure = answer["failure"]
        result = PickResult(answer["outcome"], Failure(**failure) if failure else None, seal=answer["seal"],
                            peak_ratios=answer["peak_ratios"], sim_time=answer["sim_time"],
                            dynamic_steps=answer["dynamic_steps"])
        return result, answer["lost"]

    def foresee(self, fn: Callable[[Any], dict[str, Any]]) -> dict[str, Any] | None:
        """``fn(env)`` run on a forked copy of the shadow env, its JSON-able answer; the shadow itself is left as it
        is. In the child the shadow is live on whatever ``fn`` makes of it, so ``fn`` may foresee further (the
        oracle's look past a parting push rehearses picks on the pile the push leaves). None where the shadow is
        not live or the child failed (then it stops being used this episode)."""
        if not self.live:
            return None
        read, write = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: fn on its copy of the shadow, the answer as JSON, and out
            code = 0
            try:
                os.close(read)
                data = json.dumps(fn(self.env)).encode()
                while data:
                    data = data[os.write(write, data):]
            except BaseException:  # noqa: BLE001 - the parent reads no answer and stops using the shadow
                code = 1
            finally:
                os._exit(code)  # no interpreter teardown: the parent owns every client and file
        os.close(write)
        chunks = []
        with os.fdopen(read, "rb") as pipe:
            while chunk := pipe.read(65536):
                chunks.append(chunk)
        _, status = os.waitpid(pid, 0)
        if os.waitstatus_to_exitcode(status) != 0 or not chunks:
            self.live, self.why_not = False, "a rehearsal's child process failed"
            return None
        return json.loads(b"".join(chunks))

    def close(self) -> None:
        if self.env is not None:
            self.env.close()
        self.env, self._config = None, None
        self.new_episode()

    def __del__(self) -> None:  # best effort; the env's client is private to this object
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass


def _attempt(env: Any, action: np.ndarray) -> dict[str, Any]:
    """One pick stepped on ``env`` (``ParcelPickEnv.step``, as the real env would), as ``ShadowCell.rehearse``
    answers it."""
    before = len(env.scene.parcels)
    env.step(action)
    result = env.last_result
    lost = before - len(env.scene.parcels) - (result.outcome == "success")  # the delivered parcel leaves the scene too
    return {"outcome": result.outcome, "seal": result.seal, "lost": int(lost),
            "failure": None if result.failure is None else result.failure.as_dict(),
            "peak_ratios": {k: float(v) for k, v in result.peak_ratios.items()},
            "sim_time": float(result.sim_time), "dynamic_steps": int(result.dynamic_steps)}


class _CannotFollow(Exception):
    """The shadow cannot be this episode's cell (the message says why)."""
