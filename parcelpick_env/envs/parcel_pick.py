"""ParcelPick-v0: clear a bin of parcels with a suction cup on a Kinova Gen3, one pick per step.

Observation, by ``EnvConfig.obs_mode`` (``envs/observation.py``; ``'rgbd'`` keeps only the images,
``'state_dict'`` is the privileged ground truth for the oracle). The default ``'pointcloud'`` (no ground
truth): ``points``/``normals`` (N, 3) float32, world frame, N fixed (the
camera cloud cropped to the inside of the bin, the cell's region of interest, then sampled without
replacement, or padded by repeats, with the env's ``np_random``);
``rgb`` (H, W, 3) uint8; ``depth`` (H, W, 1) float32 metres. Camera calibration is in
``info['intrinsics']`` (3x3) and ``info['extrinsics']`` (4x4 camera->world, OpenCV).

Actions:
- ``action_mode='pose'``: Box(6) = suction point (3, inside the bin region) + outward normal (3);
  the cup approaches along ``-normal`` (normalised here).
- ``action_mode='pixel'``: Box(2) in [-1, 1] = (column, row) of the depth image; the point is the
  back-projected depth there and the normal the camera's estimate at that point.
- ``action_mode='pose_push'``: Box(7) = a ``'pose'`` action and a kind in [-1, 1]: >= 0 picks as ``'pose'``
  does; < 0 is a parting push (``push.py``): the tool, vacuum off, comes down to the point and moves
  ``GraspConfig.push_distance`` along the vector's horizontal part. A push is no pick attempt:
  ``info['pushes']`` counts them (at most ``max_pushes`` an episode, ``info['pushes_left']``; later ones are
  invalid actions), its reward is 0, its outcome ``'pushed'`` when it ran, and it neither adds to nor clears
  the run of consecutive failures.

Any unusable action (wrong shape, NaN/inf, out of range, zero normal, a pixel without depth) is
answered with ``outcome='invalid_action'`` and counts as a failed attempt; it never raises, so a
policy bug cannot crash a long evaluation (``info['invalid_reason']`` says what was wrong).

One step is one physical pick attempt (see ``grasp.py``); reward 1 when a parcel is delivered.
``terminated`` when the bin is clear (``info['reason']='cleared'``) or after
``max_consecutive_failures`` failures in a row (``'consecutive_failures'``); ``truncated`` at
``max_attempts`` (``'max_attempts'``).

Known-answer scenes: ``EnvConfig.scene_factory`` (or ``reset(options={'scene_factory': f})``) is a
callable ``(sim, seed) -> Scene`` used instead of ``build_pile``, e.g. ``custom_scene.BoxScene``.
``reset(options={'scene_seed': s})`` builds the pile of ``info['scene_seed'] == s`` (a logged episode's, or a
replay's file name's) instead of one drawn from the reset seed.
Replays: with ``record_dir`` set, each episode is written to ``record_dir/episode_<k>_seed<s>.rrd``
(``self.replay_path``; ``self.recorder`` is the live ``EpisodeRecorder``).

Speed: free-space moves are collision-checked kinematically; the approach, the seal's dwell and the lift run
at ``GraspConfig.lift_dt`` and the transport at the coarser ``carry_dt``, all with fewer solver iterations than
the pile builder's; the resting pile sleeps during transport, and in the lift once the held parcel has left it
(``Simulator.sleep_scope``, docs/cell.md). The observed normals are estimated at the sampled points only
(``Camera.normals_at``).
"""

from __future__ import annotations

import dataclasses
from numbers import Real
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, TypeVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from parcelpick_env.camera.camera import Camera
from parcelpick_env.camera.frame import CameraFrame
from parcelpick_env.envs.config import EnvConfig
from parcelpick_env.envs.grasp import Failure, PickExecutor, PickResult
from parcelpick_env.envs.observation import ObservationBuilder
from parcelpick_env.envs.push import horizontal_direction, is_push_action, push
from parcelpick_env.robot.arm import Gen3Arm
from parcelpick_env.scene.scene import Scene
from parcelpick_env.sim.simulator import Simulator

if TYPE_CHECKING:  # for annotations only: at run time both are imported where first needed
    from parcelpick_env.assets.library import AssetLibrary
    from parcelpick_env.envs.replay import EpisodeRecorder

T = TypeVar("T")


def pixel_from_action(action: np.ndarray, width: int, height: int) -> tuple[int, int]:
    """The (row, col) a ``pixel``-mode action in [-1, 1]^2 (column, row) selects."""
    col = int(round((float(action[0]) + 1) / 2 * (width - 1)))
    row = int(round((float(action[1]) + 1) / 2 * (height - 1)))
    return row, col


NO_BODY = -1  # info['failure']['body'] when no other body was involved
NOT_MEASURED = -1.0  # info['seal'] when the attempt ended before the seal was judged


def _after_reset(value: T | None, name: str) -> T:
    """``value``, which ``reset()`` creates; before the first reset, a clear error naming it."""
    if value is None:
        raise RuntimeError(f"ParcelPick env has no {name} yet: call reset() first")
    return value


def step_info(result: PickResult) -> dict[str, Any]:
    """The attempt's part of ``info``, with one type per key whatever the outcome: ``NOT_MEASURED`` for a
    seal that was not judged, a zero ``contact_point`` with ``contacted=False`` when nothing was touched,
    ``NO_BODY`` and ``None`` strings for a failure that did not happen. Gymnasium's vector envs stack
    infos into typed arrays, so a key that is a float on one step and None on another breaks them; NaN
    placeholders would break the env checker's same-seed equality instead."""
    failure = result.failure.as_dict() if result.failure else dict.fromkeys(f.name for f in dataclasses.fields(Failure))
    failure["body"] = NO_BODY if failure["body"] is None else int(failure["body"])
    contacted = result.contact_point is not None
    contact = np.asarray(result.contact_point, np.float64) if contacted else np.zeros(3)
    return {"outcome": result.outcome, "failure_cause": result.failure_cause, "failure_phase": result.failure_phase,
            "failure": failure, "seal": NOT_MEASURED if result.seal is None else float(result.seal),
            "contacted": contacted, "contact_point": contact, "sim_time": float(result.sim_time)}


class ParcelPickEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}
    action_space: spaces.Box  # both action modes are boxes (see the module docstring)

    def __init__(self, config: EnvConfig | None = None, render_mode: str | None = None, **overrides: Any) -> None:
        cfg = config or EnvConfig()
        if overrides:
            cfg = dataclasses.replace(cfg, **overrides)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.config = cfg
        self.render_mode = render_mode
        # Connects (and starts EGL) at the first reset, not here: a constructed-only env (gymnasium's
        # AsyncVectorEnv builds one in the parent before forking) must not start EGL (sim/egl.py).
        self.sim = Simulator(cfg.sim)
        self.camera = Camera(cfg.camera)
        self.arm: Gen3Arm | None = None
        self.executor: PickExecutor | None = None
        self.scene: Scene | None = None
        self.frame: CameraFrame | None = None
        self.last_result: PickResult | None = None  # the last step's whole result (peak ring ratios, moves, trace)
        self.recorder: EpisodeRecorder | None = None
        self.replay_path: Path | None = None
        self._ready_q: np.ndarray | None = None
        self._library: AssetLibrary | None = None
        self._episode = -1
        self._stats: dict[str, Any] = {}

        self._observation = ObservationBuilder(cfg)  # the obs_mode's space and builder (envs/observation.py)
        self.observation_space = self._observation.space
        self._bin = cfg.bin
        if cfg.action_mode in ("pose", "pose_push"):
            lo, hi = self._bin_box()
            kind = 1 if cfg.action_mode == "pose_push" else 0  # the pick-or-push number
            self.action_space = spaces.Box(np.concatenate([lo, -np.ones(3 + kind)]).astype(np.float32),
                                           np.concatenate([hi, np.ones(3 + kind)]).astype(np.float32),
                                           dtype=np.float32)
        else:
            self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)

    # ------------------------------------------------------------------------------------ helpers
    def _bin_box(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self._bin.workspace(margin=self.config.action_margin)
        return lo, hi

    def _build_scene(self, seed: int, factory: Callable[[Simulator, int], Scene] | None) -> Scene:
        from parcelpick_env.scene.pile import build_pile, hull_fill

        cfg = self.config
        if factory is not None:
            scene = factory(self.sim, seed)
            # a hand-made scene is the request it was made with: its fill, so info's is always a number
            scene.meta.setdefault("hull_fill", hull_fill([p.asset for p in scene.parcels], scene.bin))
            return scene
        from parcelpick_env.assets.library import AssetLibrary
        from parcelpick_env.scene.config import PileConfig

        if self._library is None:
            self._library = AssetLibrary.default(cfg.asset_seed)
        pile = PileConfig(num_parcels=cfg.num_parcels, layout=cfg.layout, object_set=cfg.object_set,
                          split=cfg.split, bin=self._bin, heavy_first_mass=cfg.heavy_first_mass)
        return build_pile(self.sim, pile, seed, self._library)

    def _observe(self) -> dict[str, np.ndarray]:
        scene = _after_reset(self.scene, "scene")
        # normals only where they are observed (sample_cloud) or picked (_pixel_to_pose): Camera.normals_at
        self.frame = self.camera.capture(self.sim, scene, self.np_random, normals=False)
        return self._observation.build(self.frame, scene, self.sim, self._bin, self.np_random, self.camera.normals_at)

    def _info(self, **extra: Any) -> dict[str, Any]:
        s = self._stats
        scene, frame = _after_reset(self.scene, "scene"), _after_reset(self.frame, "camera frame")
        info = {
            "attempts": s["attempts"], "successes": s["successes"], "parcels_placed": s["placed"],
            "parcels_cleared": s["cleared"], "parcels_remaining": len(scene.parcels),
            "parcels_lost": s["lost"],
            # how the scene was built: requested = placed + skipped (no room, scattered) + lost at reset
            "parcels_requested": scene.meta.get("requested", s["placed"]),
            "parcels_skipped": scene.meta.get("skipped", 0),
            "parcels_lost_at_reset": scene.meta.get("lost", 0),
            "pile_hull_fill": scene.meta["hull_fill"],  # the request's hulls over the tote's volume
            "R_grasp": s["successes"] / s["attempts"] if s["attempts"] else 0.0,
            "R_object": s["cleared"] / s["placed"] if s["placed"] else 0.0,
            "consecutive_failures": s["consecutive"],
            "pushes": s["pushes"],  # parting pushes so far (action_mode="pose_push"); never pick attempts
            "pushes_left": self.config.max_pushes - s["pushes"],  # before a push is an invalid action
            "intrinsics": frame.intrinsics.copy(), "extrinsics": frame.extrinsics.copy(),
            "workspace": self._bin.workspace(),  # the cell's known geometry (bin floor and walls), not ground truth
            "scene_seed": scene.seed,
            **self._observation.info(),  # 'privileged' (True only in obs_mode='state_dict') and its context
        }
        info.update(extra)
        return info

    def _parse_action(self, action: Any) -> tuple[np.ndarray | None, np.ndarray | None, str | None, bool]:
        """(point, unit normal or push direction, None, whether it is a push) or (None, None, why it is invalid,
        False).

        Only real numbers are actions: numpy would turn "0.1", True and 1+0j into floats and the arm would
        execute them, so strings, booleans and complex values are refused before any conversion.
        """
        if isinstance(action, (list, tuple)) or (isinstance(action, np.ndarray) and action.dtype == object):
            items = np.asarray(action, dtype=object).ravel()
            if not all(isinstance(x, Real) and not isinstance(x, (bool, np.bool_)) for x in items):
                return None, None, "not numeric (strings, booleans and complex numbers are refused)", False
        elif np.asarray(action).dtype.kind not in "iuf":  # arrays, tensors and scalars: by dtype
            return None, None, f"not numeric (dtype {np.asarray(action).dtype} refused)", False
        try:
            a = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):
            return None, None, "not numeric", False
        if a.shape != self.action_space.shape:
            return None, None, f"shape {a.shape} != {self.action_space.shape}", False
        if not np.all(np.isfinite(a)):
            return None, None, "NaN or inf", False
        lo, hi = self.action_space.low.astype(np.float64), self.action_space.high.astype(np.float64)
        if np.any(a < lo - 1e-6) or np.any(a > hi + 1e-6):
            return None, None, "out of range", False
        if self.config.action_mode == "pixel":
            return (*self._pixel_to_pose(a), False)
        vector = a[3:6]
        norm = float(np.linalg.norm(vector))
        is_push = self.config.action_mode == "pose_push" and is_push_action(a)
        if is_push and horizontal_direction(vector) is None:
            return None, None, "push direction has no horizontal part", False
        if norm < 1e-6:
            return None, None, "zero normal", False
        return a[:3], vector / norm, None, is_push

    def _pixel_to_pose(self, a: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None, str | None]:
        frame = _after_reset(self.frame, "camera frame")
        row, col = pixel_from_action(a, frame.width, frame.height)
        lookup = np.full((frame.height, frame.width), -1, dtype=np.int64)
        lookup[frame.point_pixels[:, 0], frame.point_pixels[:, 1]] = np.arange(len(frame.points))
        k = lookup[row, col]
        if k < 0:
            return None, None, f"no depth at pixel ({row}, {col})"
        normal = self.camera.normals_at(frame, np.array([k]))[0].astype(np.float64)
        norm = float(np.linalg.norm(normal))
        if not np.isfinite(norm) or norm < 1e-6:
            return None, None, "no normal at pixel"
        return frame.points[k].astype(np.float64), normal / norm, None

    def _link_chain(self, q: np.ndarray) -> np.ndarray:
        arm = _after_reset(self.arm, "arm")
        tip, _, _, origins = arm.kin.forward(q)
        base = np.asarray(arm.config.base_position)
        return np.vstack([base, origins, tip])

    def _drop_departed(self) -> int:
        """Forget delivered parcels; remove those that fell out of the bin (``BinSpec.contains`` on the
        centre of mass, the definition the pile builder uses too). Returns how many fell out."""
        scene = _after_reset(self.scene, "scene")
        kept, lost = [], 0
        for ps in scene.parcels:
            if not self.sim.has_body(ps.body_id):
                continue
            ps.position, ps.orientation = self.sim.body_pose(ps.body_id)
            if scene.bin.contains(ps.world_com())[0]:
                kept.append(ps)
            else:
                self.sim.remove(ps.body_id)
                lost += 1
        for k, ps in enumerate(kept):
            ps.object_id = k
        scene.parcels = kept
        return lost

    def _settle_against_arm(self, steps: int = 240) -> None:
        """A parcel overhanging the near wall can overlap the arm, which joins the world after the pile
        is built: hold the arm at home and let contact push such parcels clear, then settle again."""
        arm, scene = _after_reset(self.arm, "arm"), _after_reset(self.scene, "scene")
        if arm.first_penetration(set(), depth=1e-4) is None:
            return
        arm.hold(steps, lambda: self.sim.step(1), self.sim.config.timestep)
        bodies = [ps.body_id for ps in scene.parcels]
        self.sim.settle(bodies, max_steps=self.config.grasp.max_post_settle_steps)
        lost = self._drop_departed()
        if lost:  # still part of building the scene: its own count of parcels lost, and placed
            meta = scene.meta
            meta["lost"] = meta.get("lost", 0) + lost
            meta["placed"] = len(scene.parcels)

    # ------------------------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = options or {}
        self.last_result = None
        if self.recorder is not None:
            self.recorder.close()
            self.recorder = None
        factory = options.get("scene_factory", self.config.scene_factory)
        scene_seed = int(self.np_random.integers(0, 2**31 - 1))  # drawn in any case: np_random advances alike
        if "scene_seed" in options:
            scene_seed = options["scene_seed"]
            if isinstance(scene_seed, (bool, np.bool_)) or not isinstance(scene_seed, (int, np.integer)) \
                    or not 0 <= scene_seed < 2**31 - 1:
                raise ValueError(f"reset option scene_seed must be an int in [0, 2**31 - 1), got {scene_seed!r}")
            scene_seed = int(scene_seed)
        self.scene = self._build_scene(scene_seed, factory)
        self.arm = Gen3Arm(self.sim.client, self.config.arm)
        self.executor = PickExecutor(self.sim, self.arm, self.config.grasp, self.config.suction)
        if self._ready_q is None:
            self._ready_q = self.executor.ready_pose(self.scene.bin)
        if self._ready_q is not None:
            self.executor.set_ready_seed(self._ready_q)
        self._settle_against_arm()
        self._episode += 1
        placed = len(self.scene.parcels)
        self._stats = {"attempts": 0, "successes": 0, "placed": placed, "cleared": 0, "lost": 0,
                       "consecutive": 0, "pushes": 0, "done": placed == 0}
        obs = self._observe()
        if self.config.record_dir is not None:
            from parcelpick_env.envs.replay import EpisodeRecorder

            name = f"episode_{self._episode:04d}_seed{scene_seed}.rrd"
            self.replay_path = Path(self.config.record_dir) / name
            self.recorder = EpisodeRecorder(self.replay_path, episode_id=name[:-4],
                                            max_points=self.config.record_points)
            self.recorder.log_observation(0, _after_reset(self.frame, "camera frame"), self.scene)
        return obs, self._info(reason="cleared" if placed == 0 else None)

    def step(self, action: Any):
        if getattr(self, "_closed", False):
            raise RuntimeError("ParcelPick env is closed: step() after close(); make a new env")
        if self.scene is None:
            raise RuntimeError("call reset() before step()")
        s = self._stats
        point, normal, why, is_push = self._parse_action(action)
        if is_push and s["pushes"] >= self.config.max_pushes:
            why, is_push = f"push limit reached ({self.config.max_pushes} an episode, EnvConfig.max_pushes)", False
        s["pushes" if is_push else "attempts"] += 1
        extra: dict[str, Any] = {}
        if why is not None:
            result = PickResult("invalid_action", Failure("action", condition=why))
            extra["invalid_reason"] = why
        elif point is None or normal is None:  # pragma: no cover - _parse_action gives a pose or a reason
            raise RuntimeError("ParcelPick env: the action parser returned neither a pose nor a reason")
        else:
            executor = _after_reset(self.executor, "pick executor")
            result = (push(executor, self.scene, point, normal) if is_push
                      else executor.attempt(self.scene, point, normal))
            if result.dynamic_steps > 0:
                executor.settle_pile(self.scene)
            lost = self._drop_departed()
            s["lost"] += lost
        self.last_result = result
        reward = 0.0
        if result.outcome == "success":
            s["successes"] += 1
            s["cleared"] += 1
            s["consecutive"] = 0
            reward = 1.0
        elif not is_push:
            s["consecutive"] += 1
        obs = self._observe()
        reason = None
        terminated = truncated = False
        if not self.scene.parcels:
            terminated, reason = True, "cleared"
        elif s["consecutive"] >= self.config.max_consecutive_failures:
            terminated, reason = True, "consecutive_failures"
        elif s["attempts"] >= self.config.attempt_limit:
            truncated, reason = True, "max_attempts"
        info = self._info(**step_info(result), reason=reason, **extra)
        if self.recorder is not None:
            k = s["attempts"] + s["pushes"]  # the step's index on the replay's timeline
            self.recorder.log_action(k, point, normal)
            self.recorder.log_result(k, result, link_chain=self._link_chain if self.arm else None,
                                     metrics={"R_grasp": info["R_grasp"], "R_object": info["R_object"],
                                              "reward": reward})
            self.recorder.log_observation(k, _after_reset(self.frame, "camera frame"), self.scene)
            if terminated or truncated:
                self.recorder.close()
                self.recorder = None
        return obs, reward, terminated, truncated, info

    def privileged_state(self) -> dict[str, Any]:
        """The scene's true state as ``obs_mode="state_dict"`` gives it (without the cloud), whatever this env's
        obs_mode: for evaluators that judge a pick (``eval/pick_audit.py``) and for the oracle's shadow of the cell (its
        own env, ``policies/shadow_cell.py``), never for a deployable policy's input."""
        return self._observation.state(_after_reset(self.scene, "scene"), self.sim)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self.frame is None:
            raise RuntimeError("call reset() before render()")
        return self.frame.rgb.copy()

    def close(self) -> None:
        self._closed = True  # step() then refuses clearly instead of reaching pybullet's "Not connected"
        if self.recorder is not None:
            self.recorder.close()
            self.recorder = None
        if getattr(self, "sim", None) is not None:
            self.sim.close()  # idempotent; a never-used simulator closes without connecting
