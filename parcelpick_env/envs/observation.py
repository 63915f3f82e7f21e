"""What ParcelPick-v0 observes, per ``EnvConfig.obs_mode`` (ManiSkill3's names): spaces and builders.

- ``"pointcloud"`` (default): ``points``/``normals`` (N, 3) float32, world frame, the camera cloud cropped
  to the inside of the bin and sampled to a fixed N (without replacement, or padded by repeats, with the
  env's ``np_random``); ``rgb`` (H, W, 3) uint8; ``depth`` (H, W, 1) float32 metres.
- ``"rgbd"``: ``rgb`` and ``depth`` only. The camera matrices stay in ``info['intrinsics']`` (3x3) and
  ``info['extrinsics']`` (4x4 camera->world, OpenCV), as in every mode.
- ``"state_dict"``: **privileged ground truth** read from the simulator, for the oracle
  (``policies/oracle.py``, the benchmark's ceiling) and for RL baselines that want state. No
  deployable policy may read it: a real cell has no such sensor. The env marks it with
  ``info['privileged'] = True`` (False in the other modes). Fixed shapes, padded to
  ``MAX_PARCELS`` rows; row ``k < parcel_count`` is scene object ``k`` (its segmentation label):

  ==================== ================ =====================================================
  key                  shape, dtype     meaning
  ==================== ================ =====================================================
  parcel_mask          (50,) int8       1 for a real parcel, 0 for padding (MultiBinary)
  parcel_count         () int64         how many rows are real (Discrete(51))
  parcel_position      (50, 3) float32  body-frame origin (the mesh's geometric centre), world m
  parcel_quaternion    (50, 4) float32  body orientation, xyzw (pybullet's order); pad (0,0,0,1)
  parcel_com           (50, 3) float32  centre of mass, world m
  parcel_mass          (50,) float32    kg
  parcel_asset_index   (50,) int64      index into the env's asset library; -1 for padding and
                                        for assets that are not in it (a custom scene's boxes)
  parcel_extents       (50, 3) float32  the oriented box: body-frame extents of the mesh, m
  parcel_friction      (50,) float32    the parcel's lateral friction coefficient (pybullet's)
  bin                  (7,) float32     centre x, centre y, floor z, inner size x, inner size y,
                                        wall height, wall thickness (m)
  points, normals      (N, 3) float32   the same camera cloud as ``"pointcloud"``
  ==================== ================ =====================================================

  Mesh of row k: ``library_assets(AssetLibrary.default(asset_seed))[parcel_asset_index[k]].mesh``
  (``asset_from_index``), posed by ``parcel_position``/``parcel_quaternion``; ``asset_seed`` is
  ``EnvConfig.asset_seed``, also given as ``info['asset_seed']`` in this mode, with the env's cup as
  ``info['suction']`` (``EnvConfig.suction``: its radius, material constant and seal model), and the whole
  ``EnvConfig`` as ``info['env_config']`` (with ``info['scene_seed']``, the oracle's shadow of the cell is
  built from it: ``policies/shadow_cell.py``).

Every mode captures the camera and samples the cloud, so ``np_random`` advances identically and the same
seed gives the same piles and the same episode in every mode.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable

import numpy as np
from gymnasium import spaces
from scipy.spatial.transform import Rotation

from parcelpick_env.assets.library import AssetLibrary, AssetView
from parcelpick_env.assets.parcel import ParcelAsset
from parcelpick_env.envs.config import OBS_MODES
from parcelpick_env.scene.config import MAX_FRICTION, MAX_PARCELS
from parcelpick_env.scene.scene import BinSpec

if TYPE_CHECKING:
    from parcelpick_env.camera.frame import CameraFrame
    from parcelpick_env.envs.config import EnvConfig
    from parcelpick_env.scene.scene import Scene
    from parcelpick_env.sim.simulator import Simulator

PRIVILEGED_MODES: tuple[str, ...] = ("state_dict",)
WORLD_LIMIT = 10.0  # m: bound of every world-frame coordinate in the spaces (clipped to it)
MASS_LIMIT = 100.0  # kg: bound of parcel_mass in the space, far above any parcel (clipped to it)
NOT_IN_LIBRARY = -1  # parcel_asset_index of padding rows and of assets outside the env's library
IDENTITY_XYZW = (0.0, 0.0, 0.0, 1.0)


def library_assets(library: AssetLibrary) -> AssetView:
    """The library's assets in index order (generation order: the training assets, then the test ones)."""
    return library.train + library.test


def asset_from_index(library: AssetLibrary, index: int) -> ParcelAsset:
    """The asset a ``state_dict`` row's ``parcel_asset_index`` names (its true mesh, mass and COM)."""
    assets = library_assets(library)
    if not 0 <= int(index) < len(assets):
        raise ValueError(f"asset index {index} is not in a library of {len(assets)} assets "
                         f"({NOT_IN_LIBRARY} marks padding or an asset outside the library)")
    return assets[int(index)]


def bin_vector(spec: BinSpec) -> np.ndarray:
    """The ``state_dict`` ``bin`` entry (see the module docstring for its order)."""
    return np.array([*spec.center_xy, spec.floor_z, *spec.inner_size, spec.wall_height, spec.wall_thickness],
                    dtype=np.float32)


def bin_from_vector(vector: Any) -> BinSpec:
    """The ``BinSpec`` a ``state_dict`` ``bin`` entry describes (inverse of ``bin_vector``)."""
    v = np.asarray(vector, dtype=np.float64).reshape(-1)
    if v.shape != (7,) or not np.all(np.isfinite(v)):
        raise ValueError(f"bin must be 7 finite numbers, got shape {np.shape(vector)}")
    return BinSpec(inner_size=(float(v[3]), float(v[4])), wall_height=float(v[5]), wall_thickness=float(v[6]),
                   center_xy=(float(v[0]), float(v[1])), floor_z=float(v[2]))


def _cloud_spaces(n: int) -> dict[str, spaces.Space]:
    return {"points": spaces.Box(-WORLD_LIMIT, WORLD_LIMIT, (n, 3), np.float32),
            "normals": spaces.Box(-1.0, 1.0, (n, 3), np.float32)}


def _image_spaces(height: int, width: int, far: float) -> dict[str, spaces.Space]:
    return {"rgb": spaces.Box(0, 255, (height, width, 3), np.uint8),
            "depth": spaces.Box(0.0, float(far), (height, width, 1), np.float32)}


def _state_spaces(num_assets: int) -> dict[str, spaces.Space]:
    m = MAX_PARCELS
    return {
        "parcel_mask": spaces.MultiBinary(m),
        "parcel_count": spaces.Discrete(m + 1),
        "parcel_position": spaces.Box(-WORLD_LIMIT, WORLD_LIMIT, (m, 3), np.float32),
        "parcel_quaternion": spaces.Box(-1.0, 1.0, (m, 4), np.float32),
        "parcel_com": spaces.Box(-WORLD_LIMIT, WORLD_LIMIT, (m, 3), np.float32),
        "parcel_mass": spaces.Box(0.0, MASS_LIMIT, (m,), np.float32),
        "parcel_asset_index": spaces.Box(NOT_IN_LIBRARY, max(num_assets - 1, 0), (m,), np.int64),
        "parcel_extents": spaces.Box(0.0, WORLD_LIMIT, (m, 3), np.float32),
        "parcel_friction": spaces.Box(0.0, MAX_FRICTION, (m,), np.float32),
        "bin": spaces.Box(-WORLD_LIMIT, WORLD_LIMIT, (7,), np.float32),
    }


def sample_cloud(frame: "CameraFrame", spec: BinSpec, n: int, rng: np.random.Generator,
                 normals_at: "Callable[[CameraFrame, np.ndarray], np.ndarray] | None" = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Fixed-size (n, 3) points and normals of the cloud inside the bin (the cell's region of interest).

    Sampled without replacement, or padded by repeats; an empty view gives zeros with upward normals.
    The normals are the frame's own, or, for a frame captured without them (``normals=False``),
    ``normals_at(frame, indices)`` at the sampled points only: estimating the whole cloud's (307,200
    points at 640x480) was 80% of the env's capture, for the 4,096 it observes.
    """
    roi = np.flatnonzero(spec.contains(frame.points))
    total = len(roi)
    if total == 0:
        idx = np.zeros(0, dtype=np.int64)
    elif total >= n:
        idx = roi[np.sort(rng.choice(total, n, replace=False))]
    else:
        idx = roi[np.concatenate([np.arange(total), np.sort(rng.choice(total, n - total, replace=True))])]
    points = np.zeros((n, 3), np.float32)
    normals = np.zeros((n, 3), np.float32)
    normals[:, 2] = 1.0
    if len(idx):
        points[:] = frame.points[idx]
        if len(frame.normals) == len(frame.points):
            normals[:] = frame.normals[idx]
        elif normals_at is not None:
            normals[:] = normals_at(frame, idx)
        else:
            raise ValueError("sample_cloud: the frame was captured without normals and no normals_at was given")
    np.clip(points, -WORLD_LIMIT, WORLD_LIMIT, out=points)
    np.clip(normals, -1.0, 1.0, out=normals)
    return points, normals


def state_dict(scene: "Scene", sim: "Simulator", asset_index: dict[str, int]) -> dict[str, Any]:
    """The privileged ``state_dict`` entries (without the cloud), with poses read live from the simulator."""
    m = MAX_PARCELS
    parcels = [ps for ps in scene.parcels if sim.has_body(ps.body_id)]
    if len(parcels) > m:
        raise ValueError(f"state_dict holds at most MAX_PARCELS={m} parcels, the scene has {len(parcels)}")
    k = len(parcels)
    position = np.zeros((m, 3))
    quaternion = np.tile(np.asarray(IDENTITY_XYZW), (m, 1))
    com = np.zeros((m, 3))
    mass = np.zeros(m)
    extents = np.zeros((m, 3))
    friction = np.zeros(m)
    index = np.full(m, NOT_IN_LIBRARY, dtype=np.int64)
    if k:
        poses = [sim.body_pose(ps.body_id) for ps in parcels]
        position[:k] = [pos for pos, _ in poses]
        quaternion[:k] = [orn for _, orn in poses]
        body_com = np.array([ps.asset.com for ps in parcels], dtype=np.float64)
        com[:k] = Rotation.from_quat(quaternion[:k]).apply(body_com) + position[:k]
        mass[:k] = [ps.asset.mass for ps in parcels]
        extents[:k] = [ps.asset.extents for ps in parcels]
        friction[:k] = [ps.friction for ps in parcels]
        index[:k] = [asset_index.get(ps.asset.asset_id, NOT_IN_LIBRARY) for ps in parcels]
    mask = np.zeros(m, dtype=np.int8)
    mask[:k] = 1
    return {
        "parcel_mask": mask,
        "parcel_count": np.int64(k),
        "parcel_position": np.clip(position, -WORLD_LIMIT, WORLD_LIMIT).astype(np.float32),
        "parcel_quaternion": np.clip(quaternion, -1.0, 1.0).astype(np.float32),
        "parcel_com": np.clip(com, -WORLD_LIMIT, WORLD_LIMIT).astype(np.float32),
        "parcel_mass": np.clip(mass, 0.0, MASS_LIMIT).astype(np.float32),
        "parcel_asset_index": index,
        "parcel_extents": np.clip(extents, 0.0, WORLD_LIMIT).astype(np.float32),
        "parcel_friction": np.clip(friction, 0.0, MAX_FRICTION).astype(np.float32),
        "bin": bin_vector(scene.bin),
    }


class ObservationBuilder:
    """The observation space of one ``obs_mode`` and the builder of its observations."""

    def __init__(self, config: "EnvConfig") -> None:
        if config.obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {config.obs_mode!r}")
        self.config = config
        self.mode = config.obs_mode
        self.privileged = self.mode in PRIVILEGED_MODES
        self._asset_index: dict[str, int] | None = None
        cam = config.camera
        images = _image_spaces(cam.height, cam.width, cam.far)
        cloud = _cloud_spaces(config.num_points)
        if self.mode == "pointcloud":
            layout = {**cloud, **images}
        elif self.mode == "rgbd":
            layout = images
        else:
            layout = {**_state_spaces(len(self._library())), **cloud}
        self.space = spaces.Dict(layout)

    def _library(self) -> AssetLibrary:
        return AssetLibrary.default(self.config.asset_seed)

    def _index(self) -> dict[str, int]:
        if self._asset_index is None:
            self._asset_index = {asset_id: i for i, asset_id in enumerate(library_assets(self._library()).ids)}
        return self._asset_index

    def state(self, scene: "Scene", sim: "Simulator") -> dict[str, Any]:
        """The privileged ``state_dict`` entries of the live scene, in any mode (``ParcelPickEnv.privileged_state``)."""
        return state_dict(scene, sim, self._index())

    def build(self, frame: "CameraFrame", scene: "Scene", sim: "Simulator", spec: BinSpec, rng: np.random.Generator,
              normals_at: "Callable[[CameraFrame, np.ndarray], np.ndarray] | None" = None) -> dict[str, Any]:
        """One observation. The cloud is sampled in every mode, so ``rng`` advances the same way; a frame
        without normals gets them from ``normals_at`` at the sampled points (``sample_cloud``)."""
        points, normals = sample_cloud(frame, spec, self.config.num_points, rng, normals_at)
        if self.mode == "state_dict":
            return {**self.state(scene, sim), "points": points, "normals": normals}
        images = {"rgb": frame.rgb.astype(np.uint8), "depth": frame.depth[..., None].astype(np.float32)}
        if self.mode == "rgbd":
            return images
        return {"points": points, "normals": normals, **images}

    def info(self) -> dict[str, Any]:
        """Entries every ``info`` carries: whether the observation is privileged, and in that case what
        a privileged reader needs to interpret it (the asset library's seed and the env's physical cup) and
        to model the cell (the env's whole ``EnvConfig``: the oracle's shadow cell is built from it)."""
        if not self.privileged:
            return {"privileged": False}
        return {"privileged": True, "asset_seed": int(self.config.asset_seed), "suction": self.config.suction,
                "env_config": self.config}
