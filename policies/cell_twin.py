"""A twin of the pick cell, on which the privileged oracle asks the cell's own planner about a pick, and rehearses it.

The oracle's reach checks (``policies/oracle.py``, ``ArmReach``) are fast models of the arm alone. The cell
also refuses picks for reasons those models cannot see: a wrist inside the tote's wall at every hover the IK
finds, a descent that sweeps a link through a neighbour, a lift whose IK branch jumps. ``CellTwin`` builds the
tote, the Gen3 and every parcel, each as the simulator collides it (``Simulator.add_parcel``: the asset's
hull, mass and centre of mass, the simulator's margin, the parcel's friction), in a private pybullet DIRECT
client, posed from the privileged ``state_dict`` observation. ``refusal`` asks ``PickExecutor.refusal`` there:
the env's own plan, run on the same geometry without dynamics, the cell's verdict before it moves.
``rehearse`` runs the env's whole attempt there, dynamics and all (the seal, the hold, a neighbour's drag in
the lift), then poses the twin again as observed; ``rehearse_push`` runs a parting push (``envs/push.py``) and
returns the pile it leaves, as a ``state_dict`` the oracle can decide on. What it cannot know: the pile's contact
history (the twin's contacts start fresh from float32 poses, so a chaotic lift may end otherwise in the env), and
a custom scene's fixtures, which the ``state_dict`` does not carry.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.envs.config import EnvConfig
from parcelpick_env.envs.custom_scene import box_asset
from parcelpick_env.envs.grasp import Failure, PickExecutor, PickResult
from parcelpick_env.envs.observation import asset_from_index, bin_from_vector, library_assets, state_dict
from parcelpick_env.envs.push import push
from parcelpick_env.robot.arm import Gen3Arm
from parcelpick_env.scene.scene import BinSpec, ParcelState, Scene
from parcelpick_env.sim.simulator import Simulator


@dataclasses.dataclass(frozen=True)
class PoseJitter:
    """A small random error on every parcel's pose, drawn from ``rng``: a position error of ``position`` (m,
    standard deviation per axis) and a turn about a random axis of ``angle_deg`` (standard deviation per axis of
    the rotation vector). The twin's poses are exact to float32, its contacts are not: they start fresh."""

    rng: np.random.Generator
    position: float
    angle_deg: float

    def apply(self, sim: Simulator, scene: Scene) -> None:
        """Move every parcel of ``scene`` in ``sim`` by one draw (velocities zeroed), and its ``ParcelState``."""
        n = len(scene.parcels)
        shifts = self.rng.normal(0.0, self.position, size=(n, 3))
        turns = Rotation.from_rotvec(self.rng.normal(0.0, np.radians(self.angle_deg), size=(n, 3)))
        for parcel, shift, turn in zip(scene.parcels, shifts, turns):
            parcel.position = np.asarray(parcel.position, dtype=np.float64) + shift
            parcel.orientation = (turn * Rotation.from_quat(parcel.orientation)).as_quat()
            sim.set_body_pose(parcel.body_id, parcel.position, parcel.orientation)


class CellTwin:
    """The cell's tote, arm and parcels, posed by ``sync``; ``refusal`` is the cell's plan, ``rehearse`` its attempt."""

    def __init__(self, config: EnvConfig | None = None) -> None:
        self.config = config or EnvConfig()
        self._sim: Simulator | None = None
        self._executor: PickExecutor | None = None
        self._bin: BinSpec | None = None
        self._bodies: list[int] = []
        self._synced: Mapping[str, Any] | None = None
        self._library: AssetLibrary | None = None
        self.scene: Scene | None = None

    def _world(self, spec: BinSpec) -> PickExecutor:
        """The client, tote and arm, made on first use and again only if the tote changes."""
        if self._executor is not None and spec == self._bin:
            return self._executor
        self.close()
        cfg = self.config
        self._sim = Simulator(dataclasses.replace(cfg.sim, egl_rendering=False))
        self._sim.add_bin(spec)
        arm = Gen3Arm(self._sim.client, cfg.arm)
        self._executor = PickExecutor(self._sim, arm, cfg.grasp, cfg.suction)
        ready = self._executor.ready_pose(spec)  # the env's
        if ready is not None:
            self._executor.set_ready_seed(ready)
        self._bin = spec
        return self._executor

    def sync(self, obs: Mapping[str, Any], library: AssetLibrary) -> None:
        """Pose the twin as the ``state_dict`` observation ``obs`` has the pile (library assets by index, a
        parcel outside the library as its oriented box); nothing to do for the observation it holds."""
        if obs is self._synced and library is self._library:
            return
        spec = bin_from_vector(obs["bin"])
        executor = self._world(spec)
        sim = executor.sim
        for body in self._bodies:
            if sim.has_body(body):  # a rehearsal releases the parcel it carried off
                sim.remove(body)
        self._bodies = []
        executor.arm.home()  # where the env's arm starts every attempt (its retreat ends there)
        rows = np.flatnonzero(np.asarray(obs["parcel_mask"]).astype(bool))
        parcels = []
        for k, row in enumerate(rows):
            index = int(np.asarray(obs["parcel_asset_index"])[row])
            asset = (asset_from_index(library, index) if index >= 0
                     else box_asset(np.asarray(obs["parcel_extents"], dtype=np.float64)[row],
                                    float(np.asarray(obs["parcel_mass"])[row])))
            position = np.asarray(obs["parcel_position"], dtype=np.float64)[row]
            orientation = np.asarray(obs["parcel_quaternion"], dtype=np.float64)[row]
            friction = float(np.asarray(obs["parcel_friction"])[row])
            body = sim.add_parcel(asset, position, orientation, friction)
            self._bodies.append(body)
            parcels.append(ParcelState(k, body, asset, position, orientation, friction))
        self.scene = Scene(parcels=parcels, bin=spec, seed=0, layout="twin", object_set="twin", split="test")
        self._synced, self._library = obs, library

    def refusal(self, point: np.ndarray, normal: np.ndarray) -> Failure | None:
        """Why the cell would refuse this pick before it moves (``PickExecutor.refusal``), or None."""
        executor, scene = self._require()
        return executor.refusal(scene, point, normal)

    def rehearse(self, point: np.ndarray, normal: np.ndarray, jitter: PoseJitter | None = None) -> PickResult:
        """The whole attempt on the twin, dynamics and all (``PickExecutor.attempt``: seal, hold checks, the
        neighbours' drag), as the env would run it from this pile; the twin is then posed again as synced.
        ``jitter`` first moves every parcel by a small random pose error (``PoseJitter``): a pick that holds
        only on the pile exactly as synced is one the cell's own contact history may drop."""
        executor, scene = self._require()
        try:
            if jitter is not None:
                jitter.apply(executor.sim, scene)
            return executor.attempt(scene, point, normal)
        finally:
            obs, library = self._synced, self._library
            self._synced = None
            if obs is not None and library is not None:
                self.sync(obs, library)

    def rehearse_push(self, start: np.ndarray, direction: np.ndarray) -> tuple[PickResult, dict[str, Any] | None]:
        """A parting push on the twin (``envs/push.py``), the pile then settled as the env settles it after a step,
        and the ``state_dict`` of the pile it leaves (the synced observation with every parcel's pose and centre
        of mass as they came to rest), or None where a parcel left the tote or the push did not run. The twin is
        then posed again as synced."""
        executor, scene = self._require()
        obs, library = self._synced, self._library
        try:
            result = push(executor, scene, start, direction)
            executor.settle_pile(scene)
            if result.outcome != "pushed" or obs is None or library is None:
                return result, None
            index = {asset_id: i for i, asset_id in enumerate(library_assets(library).ids)}
            after = {**obs, **state_dict(scene, executor.sim, index)}  # poses and centres of mass read live
            inside = scene.bin.contains(after["parcel_com"][: len(scene.parcels)].astype(np.float64))
            return result, after if bool(np.all(inside)) else None
        finally:
            self._synced = None
            if obs is not None and library is not None:
                self.sync(obs, library)

    def lifts(self, point: np.ndarray, normal: np.ndarray, top: float) -> bool:
        """Whether the straight lift from the contact ``point`` up to height ``top``, tool on -``normal``, solves
        by the cell's line rule (``Gen3Arm.line_path``: IK every 1.5 cm, no branch jump, yaw free) from an IK
        answer at the contact on either branch the cell's plan may take (the ready pose's, then the Kinova
        home's). Stricter than the plan's own test (``PickExecutor._lift_solves``, from the approach's last
        configuration), which passed a pick on a face tilted 25 deg whose lift then drove joint 4 to its limit
        10-12 cm up (`unreachable: lift, ik jumped 1.01 rad`, rectangular stacked episode 3 of the report)."""
        executor, _ = self._require()
        arm = executor.arm
        axis = -np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
        point = np.asarray(point, dtype=np.float64)
        end = np.array([point[0], point[1], float(top)])
        for seed in (executor.ready_q, np.asarray(arm.config.ik_seed, dtype=np.float64)):
            q = arm.ik(point, axis, seed=seed)
            if q is not None and arm.line_path(q, end, axis)[0] is not None:
                return True
        return False

    def _require(self) -> tuple[PickExecutor, Scene]:
        if self._executor is None or self.scene is None:
            raise RuntimeError("CellTwin asked about a pick before sync")
        return self._executor, self.scene

    def close(self) -> None:
        if self._sim is not None:
            self._sim.close()
        self._sim, self._executor, self._bin, self._bodies = None, None, None, []
        self._synced, self._library, self.scene = None, None, None

    def __del__(self) -> None:  # best effort; the client is private to this object
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass
