"""One GraspNet/SuctionNet view -> the Record that ``dataset/`` serves (``dataset/annotate.py``'s keys).

A view is ``scenes/scene_XXXX/<camera>/`` at one annotation id. Its depth PNG (``factor_depth`` units per
metre, from ``meta/XXXX.mat``) is back-projected with the view's intrinsics and carried into the table
frame (``cam0_wrt_table.npy @ camera_poses.npy[ann_id]``), which plays the world frame: z up, table top
at z = 0, gravity -z, as suctionnetAPI's evaluator assumes. Points are farthest-point sampled
(``parcelpick_env.farthest_points``, as ``dataset/annotate.py``) and get camera normals
(``parcelpick_env.camera.normals``).

Labels come from SuctionNet's own files: each object's seal samples (``seal_label/XXX_seal.npz``, model
frame) are posed by the view's annotation XML; every cloud point on that object (label PNG) takes the
seal score of its nearest sample among those facing the camera, and that sample's wrench score
(``wrench_label/XXXX_wrench.npz``) and collision flag (``suction_collision_label/XXXX_collision.npz``,
and the seal file's own ``collision``).
Points farther than ``max_label_distance`` from every sample, and points off every object, are labelled
0 in every channel. SuctionNet has no visibility label: 1 unless a ParcelPick sidecar carries it.

Trees written by ``dataset.suctionnet.writer`` also hold a sidecar per view
(``<camera>/parcelpick/XXXX.npz``): the sampled pixels, the camera normals, and the per-parcel fields
that SuctionNet's layout has no place for (asset ids, masses, the bin, seeds ...). With it, a view reads
back to the record it was written from; without it (real SuctionNet data) the record names its
SuctionNet models instead (``suctionnet_root``, ``object_model_ids``).
"""

from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from dataset.storage import Record
from dataset.suctionnet.layout import (
    LABEL_OFFSET,
    Layout,
    SuctionNetLayoutError,
    load_mat,
    load_npy,
    load_npz,
    positional,
    read_annotation,
    read_png,
    scalar,
    split_of_scene,
)
from parcelpick_env.farthest_points import fixed_size_sample

SOURCE = "suctionnet"
# The label set a view carries (dataset.torch_dataset.label_key): SuctionNet's own seal / wrench / collision labels
LABEL_SET = "suctionnet"
ASSET_PREFIX = "suctionnet:"  # object_asset_ids of SuctionNet models: 'suctionnet:017' (not in AssetLibrary)
CATEGORY = "suctionnet"  # SuctionNet objects have no parcel category
# The table suctionnetAPI's evaluator adds (1 m x 1 m, 5 cm thick, top at z = 0) as a BinSpec: its floor is
# that slab (``BinSpec.floor_meshes``), its walls 1 mm high, so they stand in for no real obstacle.
TABLE_BIN = {"center_xy": [0.0, 0.0], "floor_z": 0.0, "inner_size": [1.0, 1.0], "wall_height": 1e-3,
             "wall_thickness": 0.05}
# A seal sample whose outward normal makes a cosine below this with the direction to the camera faces away
# from it (slightly below 0: samples seen edge-on, as on a box's side, still count).
FACING_COSINE = -0.1
# Record keys a ParcelPick sidecar restores as they were written (nothing in SuctionNet's files holds them).
SIDECAR_PASSTHROUGH = ("object_asset_ids", "object_categories", "object_mass", "object_com", "object_friction",
                       "object_visibility", "bin_spec", "library_seed", "scene_seed", "pile_seed", "split", "layout",
                       "object_set", "rgb_noise_std", "bbox_center", "bbox_extent", "bbox_rotation", "bbox_corners")


@dataclass(frozen=True)
class ReaderConfig:
    """How a view becomes a record. ``num_points`` is the paper's 16,384 by default; a view with a ParcelPick
    sidecar keeps the pixels it was labelled at instead."""

    num_points: int = 16384
    max_label_distance: float = 0.005  # m: a cloud point farther from every seal sample is unlabelled (0)
    normal_knn: int = 30
    fps_presample: float = 2.0  # as GenerationConfig.fps_presample
    table_half_size: float = 0.5  # m: points kept over the evaluator's 1 m table (table frame |x|, |y|)
    table_tolerance: float = 0.02  # m: and above z = -this
    depth_ratio_tolerance: float = 2.0  # observed / annotated object depth outside [1/t, t]: wrong depth factor
    seed: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.num_points, int) or self.num_points < 1:
            raise ValueError(f"ReaderConfig.num_points must be a positive int, got {self.num_points!r}")
        for name in ("max_label_distance", "table_half_size", "table_tolerance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ReaderConfig.{name} must be > 0, got {getattr(self, name)!r}")
        if not self.depth_ratio_tolerance > 1:
            raise ValueError(f"ReaderConfig.depth_ratio_tolerance must be > 1, got {self.depth_ratio_tolerance!r}")
        if not isinstance(self.normal_knn, int) or self.normal_knn < 3:
            raise ValueError(f"ReaderConfig.normal_knn must be an int >= 3, got {self.normal_knn!r}")
        if self.seed < 0:
            raise ValueError(f"ReaderConfig.seed must be >= 0, got {self.seed!r}")


def _rigid(T: np.ndarray, path: Path, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise SuctionNetLayoutError(f"{path}: {what} must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or abs(np.linalg.det(R) - 1) > 1e-3 \
            or not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
        raise SuctionNetLayoutError(f"{path}: {what} is not a rigid transform")
    return T


def pose_matrix(translation: np.ndarray, quat_wxyz: np.ndarray) -> np.ndarray:
    """4x4 from a translation and a transforms3d-order (w, x, y, z) quaternion, as the XML stores it."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(np.roll(np.asarray(quat_wxyz, dtype=np.float64), -1)).as_matrix()
    T[:3, 3] = translation
    return T


def _camera(layout: Layout, scene: int, camera: str, ann_id: int
            ) -> tuple[np.ndarray, float, np.ndarray, dict[str, np.ndarray], Path]:
    """Intrinsics, depth factor, camera-to-table transform, the meta dict and its path."""
    meta_path = layout.view_file(scene, camera, "meta", ann_id)
    meta = load_mat(meta_path, "meta file", ("intrinsic_matrix", "factor_depth"))
    try:
        factor = scalar(meta["factor_depth"])
    except ValueError as exc:
        raise SuctionNetLayoutError(f"{meta_path}: factor_depth {exc}") from exc
    if not np.isfinite(factor) or factor <= 0:
        raise SuctionNetLayoutError(f"{meta_path}: factor_depth must be a positive number, got {factor}")
    K = np.asarray(meta["intrinsic_matrix"], dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 \
            or not np.allclose(K[2], [0, 0, 1]):
        raise SuctionNetLayoutError(f"{meta_path}: intrinsic_matrix is not a pinhole matrix: {K.tolist()}")
    camk_path = layout.camera_file(scene, camera, "camK.npy")
    if camk_path.exists():
        camk = load_npy(camk_path, "camera intrinsics")
        if camk.shape != (3, 3) or not np.allclose(camk, K, atol=1e-3):
            raise SuctionNetLayoutError(f"{camk_path}: intrinsics differ from {meta_path}'s intrinsic_matrix")
    poses_path = layout.camera_file(scene, camera, "camera_poses.npy")
    poses = load_npy(poses_path, "camera poses")
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not 0 <= ann_id < len(poses):
        raise SuctionNetLayoutError(f"{poses_path}: camera poses of shape {poses.shape} have no view {ann_id}")
    align_path = layout.camera_file(scene, camera, "cam0_wrt_table.npy")
    align = _rigid(load_npy(align_path, "camera-0-to-table transform"), align_path, "cam0_wrt_table")
    extrinsics = align @ _rigid(poses[ann_id], poses_path, f"camera pose {ann_id}")
    return K, factor, extrinsics, meta, meta_path


def _objects(layout: Layout, scene: int, camera: str, ann_id: int, meta: dict[str, np.ndarray], meta_path: Path
             ) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Model ids (M,), names, and model-to-camera poses (M, 4, 4) from the annotation XML."""
    xml_path = layout.view_file(scene, camera, "annotations", ann_id)
    objects = read_annotation(xml_path)
    ids = np.array([o[0] for o in objects], dtype=np.int64)
    if len(set(ids.tolist())) != len(ids):
        raise SuctionNetLayoutError(f"{xml_path}: an object id appears twice: {ids.tolist()}")
    for obj_id in ids:
        mesh = layout.model_mesh(int(obj_id))
        if obj_id < 0 or not mesh.is_file():
            raise SuctionNetLayoutError(f"{xml_path}: unknown object id {int(obj_id)} (no model {mesh})")
    if "cls_indexes" in meta:
        meta_ids = np.asarray(meta["cls_indexes"]).reshape(-1).astype(np.int64) - LABEL_OFFSET
        if sorted(meta_ids.tolist()) != sorted(ids.tolist()):
            raise SuctionNetLayoutError(f"{meta_path}: cls_indexes name objects {meta_ids.tolist()}, "
                                        f"{xml_path} annotates {ids.tolist()}")
    poses = np.stack([pose_matrix(o[2], o[3]) for o in objects]) if objects else np.zeros((0, 4, 4))
    return ids, [o[1] for o in objects], poses


def _frozen(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    for array in arrays.values():
        array.setflags(write=False)
    return arrays


def _stamp(*paths: Path) -> tuple[tuple[int, int] | None, ...]:
    """(mtime, size) of each file: part of every cache key below, so a rewritten file is read again."""
    return tuple((st.st_mtime_ns, st.st_size) if (st := _stat(p)) is not None else None for p in paths)


def _stat(path: Path) -> os.stat_result | None:
    try:
        return path.stat()
    except OSError:
        return None


@functools.lru_cache(maxsize=256)
def _seal_samples(root: Path, obj_id: int, stamp: tuple) -> dict[str, np.ndarray]:
    """One object's seal label (cached: every view of every scene holding the object reads it)."""
    path = Layout(root).seal_label(obj_id)
    data = load_npz(path, f"seal label of object {obj_id}", ("points", "normals", "scores"))
    n = len(data["points"])
    if data["points"].shape != (n, 3) or data["normals"].shape != (n, 3) or data["scores"].shape != (n,) \
            or ("collision" in data and data["collision"].shape != (n,)):
        raise SuctionNetLayoutError(f"{path}: points, normals, scores (and collision) disagree in length")
    return _frozen(data)


@functools.lru_cache(maxsize=16)
def _scene_labels(root: Path, scene: int, count: int, stamp: tuple
                  ) -> tuple[Path, list[np.ndarray], Path, list[np.ndarray]]:
    """A scene's wrench and collision arrays, one per object (cached: the scene's 256 views share them)."""
    layout = Layout(root)
    wrench_path, collision_path = layout.wrench_label(scene), layout.collision_label(scene)
    wrenches = positional(_frozen(load_npz(wrench_path, f"wrench label of scene {scene}")), count, wrench_path,
                          "wrench label")
    collisions = positional(_frozen(load_npz(collision_path, f"collision label of scene {scene}")), count,
                            collision_path, "collision label")
    return wrench_path, wrenches, collision_path, collisions


@functools.lru_cache(maxsize=256)
def _model_centroid(root: Path, obj_id: int, stamp: tuple) -> np.ndarray | None:
    """Centroid of the dense model sample, the centre suctionnetAPI's wrench score uses; None without one."""
    path = Layout(root).dense_points(obj_id)
    if not path.is_file():
        return None
    points = load_npz(path, f"dense point cloud of object {obj_id}", ("points",))["points"]
    return np.asarray(points, dtype=np.float64).reshape(-1, 3).mean(axis=0)


def _check_depth_factor(depth: np.ndarray, seg: np.ndarray, poses: np.ndarray, factor: float,
                        meta_path: Path, tolerance: float) -> None:
    """A wrong factor_depth scales every depth: compare observed depth on the objects with the annotated poses."""
    on_objects = (seg >= 0) & (depth > 0)
    if not on_objects.any() or len(poses) == 0:
        return
    seen = np.unique(seg[on_objects])
    observed = float(np.median(depth[on_objects]))
    annotated = float(np.median(poses[seen, 2, 3]))
    if annotated <= 0 or not 1 / tolerance <= observed / annotated <= tolerance:
        raise SuctionNetLayoutError(f"{meta_path}: factor_depth {factor:g} puts the objects at {observed:.3f} m, "
                                    f"their annotated poses at {annotated:.3f} m: wrong depth factor")


def _view_images(layout: Layout, scene: int, camera: str, ann_id: int, ids: np.ndarray, factor: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RGB (H, W, 3) uint8, metric depth (H, W) float32, and segmentation as object index (-1 elsewhere)."""
    rgb_path, depth_path, label_path = (layout.view_file(scene, camera, kind, ann_id)
                                        for kind in ("rgb", "depth", "label"))
    rgb, raw = read_png(rgb_path, "RGB image"), read_png(depth_path, "depth image")
    label = read_png(label_path, "label image")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise SuctionNetLayoutError(f"{depth_path}: depth image must be single-channel 16-bit, "
                                    f"got {raw.dtype} {raw.shape}")
    if rgb.ndim != 3 or rgb.shape[:2] != raw.shape or rgb.shape[2] < 3:
        raise SuctionNetLayoutError(f"{rgb_path}: RGB image of shape {rgb.shape} does not match depth {raw.shape}")
    if label.ndim != 2 or label.shape != raw.shape:
        raise SuctionNetLayoutError(f"{label_path}: label image of shape {label.shape} "
                                    f"does not match depth {raw.shape}")
    lookup = np.full(int(max(label.max(initial=0), ids.max(initial=-1) + LABEL_OFFSET)) + 1, -1, dtype=np.int64)
    lookup[ids + LABEL_OFFSET] = np.arange(len(ids))
    seg = lookup[label.astype(np.int64)]
    unknown = (label > 0) & (seg < 0)
    if unknown.any():
        stray = sorted(set((label[unknown].astype(np.int64) - LABEL_OFFSET).tolist()))
        raise SuctionNetLayoutError(f"{label_path}: unknown object id(s) {stray} "
                                    f"(the view's annotation lists {ids.tolist()})")
    return np.ascontiguousarray(rgb[..., :3]), (raw.astype(np.float64) / factor).astype(np.float32), seg


def _labels(layout: Layout, scene: int, ids: np.ndarray, world_from_model: np.ndarray, camera: np.ndarray,
            points: np.ndarray, object_ids: np.ndarray, max_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) seal, wrench, collision-free per point, and each object's model centroid in the world (M, 3)."""
    root = layout.root.resolve()
    wrench_path, wrenches, collision_path, collisions = _scene_labels(
        root, int(scene), len(ids), _stamp(layout.wrench_label(scene), layout.collision_label(scene)))
    out = np.zeros((len(points), 3), dtype=np.float32)
    centroids = np.zeros((len(ids), 3))
    for i, obj_id in enumerate(ids):
        seal = _seal_samples(root, int(obj_id), _stamp(layout.seal_label(int(obj_id))))
        n = len(seal["points"])
        for path, array, what in ((wrench_path, wrenches[i], "wrench"), (collision_path, collisions[i], "collision")):
            if array.shape != (n,):
                raise SuctionNetLayoutError(f"{path}: {what} of object {int(obj_id)} (arr_{i}) has shape "
                                            f"{array.shape}, "
                                            f"its seal label has {n} samples")
        samples = seal["points"].astype(np.float64) @ world_from_model[i, :3, :3].T + world_from_model[i, :3, 3]
        centre = _model_centroid(root, int(obj_id), _stamp(layout.dense_points(int(obj_id))))
        if centre is None:
            centre = seal["points"].astype(np.float64).mean(axis=0) if n else np.zeros(3)
        centroids[i] = world_from_model[i, :3, :3] @ centre + world_from_model[i, :3, 3]
        on = np.flatnonzero(object_ids == i)
        # Only samples on the side the camera sees: a point on a thin object's front takes no back-face label.
        normals = seal["normals"].astype(np.float64) @ world_from_model[i, :3, :3].T
        towards = camera - samples
        facing = np.flatnonzero(np.sum(normals * towards, axis=1) >= FACING_COSINE * np.linalg.norm(normals, axis=1)
                                * np.linalg.norm(towards, axis=1))
        if len(facing) == 0 or len(on) == 0:
            continue
        distance, nearest = cKDTree(samples[facing]).query(points[on].astype(np.float64))
        hit = distance <= max_distance
        rows, j = on[hit], facing[nearest[hit]]
        collides = collisions[i].astype(bool)
        if "collision" in seal:
            collides = collides | seal["collision"].astype(bool)
        out[rows, 0] = seal["scores"][j]
        out[rows, 1] = wrenches[i][j]
        out[rows, 2] = (~collides[j]).astype(np.float32)
    return out, centroids


def _sample(points: np.ndarray, keep: np.ndarray, config: ReaderConfig, scene: int, ann_id: int) -> np.ndarray:
    candidates = np.flatnonzero(keep)
    if len(candidates) == 0:
        raise SuctionNetLayoutError(f"scene {scene} view {ann_id}: no valid depth over the table")
    rng = np.random.default_rng([config.seed, scene, ann_id])
    return candidates[fixed_size_sample(points[candidates], config.num_points, rng, config.fps_presample)]


def read_view(root: str | os.PathLike, scene: int, camera: str, ann_id: int,
              config: ReaderConfig = ReaderConfig()) -> Record:
    """The record of one view; ``SuctionNetLayoutError`` naming the file if anything is missing or wrong."""
    from parcelpick_env.camera.normals import organized_normals

    layout = Layout(root)
    if not layout.camera_dir(scene, camera).is_dir():
        raise SuctionNetLayoutError(f"{layout.camera_dir(scene, camera)}: no such scene/camera directory")
    K, factor, extrinsics, meta, meta_path = _camera(layout, scene, camera, ann_id)
    ids, names, cam_from_model = _objects(layout, scene, camera, ann_id, meta, meta_path)
    rgb, depth, seg = _view_images(layout, scene, camera, ann_id, ids, factor)
    _check_depth_factor(depth, seg, cam_from_model, factor, meta_path, config.depth_ratio_tolerance)

    valid = depth > 0
    rows, cols = np.nonzero(valid)
    z = depth[rows, cols].astype(np.float64)
    cam = np.stack([(cols - K[0, 2]) / K[0, 0] * z, (rows - K[1, 2]) / K[1, 1] * z, z], axis=1)
    R, t = extrinsics[:3, :3], extrinsics[:3, 3]
    world = cam @ R.T + t
    index_of = np.full(depth.shape, -1, dtype=np.int64)
    index_of[rows, cols] = np.arange(len(rows))

    sidecar_path = layout.view_file(scene, camera, "parcelpick", ann_id)
    sidecar = (load_npz(sidecar_path, "ParcelPick sidecar", ("point_pixels", "normals"))
               if sidecar_path.exists() else None)
    if sidecar is not None:
        pixels = sidecar["point_pixels"].astype(np.int64)
        inside = (pixels.ndim == 2 and pixels.shape[1] == 2 and np.all(pixels >= 0)
                  and np.all(pixels < np.array(depth.shape)))
        chosen = index_of[pixels[:, 0], pixels[:, 1]] if inside else np.array([-1])
        if np.any(chosen < 0) or sidecar["normals"].shape != pixels.shape[:1] + (3,):
            raise SuctionNetLayoutError(f"{sidecar_path}: point_pixels/normals do not match valid pixels "
                                        f"of the depth image")
        normals = sidecar["normals"].astype(np.float64) @ R.T
    else:
        over_table = (np.all(np.abs(world[:, :2]) <= config.table_half_size, axis=1)
                      & (world[:, 2] >= -config.table_tolerance))
        chosen = _sample(world, over_table, config, scene, ann_id)
        image = np.zeros(depth.shape + (3,))
        image[rows, cols] = world
        normals = organized_normals(image, valid, config.normal_knn, t)[chosen]
    points = world[chosen]
    object_ids = seg[rows[chosen], cols[chosen]].astype(np.int32)

    world_from_model = extrinsics[None] @ cam_from_model
    labels3, centroids = _labels(layout, scene, ids, world_from_model, t, points, object_ids,
                                 config.max_label_distance)
    visibility = np.ones(len(ids))
    if sidecar is not None and "object_visibility" in sidecar:
        visibility = sidecar["object_visibility"].astype(np.float64).reshape(-1)
        if visibility.shape != ids.shape:
            raise SuctionNetLayoutError(f"{sidecar_path}: object_visibility has {visibility.size} entries "
                                        f"for {len(ids)} objects")
    point_vis = np.where(object_ids >= 0, visibility[np.maximum(object_ids, 0)], 0.0)
    labels = np.concatenate([labels3, point_vis[:, None].astype(np.float32)], axis=1)
    labels[object_ids < 0] = 0.0

    quat = Rotation.from_matrix(world_from_model[:, :3, :3]).as_quat() if len(ids) else np.zeros((0, 4))
    record: Record = {
        "points": points.astype(np.float32),
        "normals": normals.astype(np.float32),
        "labels": labels,
        "score": labels.prod(axis=1).astype(np.float32),
        "object_ids": object_ids,
        "point_pixels": np.stack([rows[chosen], cols[chosen]], axis=1).astype(np.int32),
        "colors": rgb[rows[chosen], cols[chosen]],
        "object_asset_ids": np.array([f"{ASSET_PREFIX}{i:03d}" for i in ids], dtype=str).reshape(-1),
        "object_categories": np.array([CATEGORY] * len(ids), dtype=str).reshape(-1),
        "object_poses": np.concatenate([world_from_model[:, :3, 3], quat], axis=1).reshape(-1, 7),
        "object_com_world": centroids,
        "object_visibility": visibility,
        "object_model_ids": ids,
        "object_names": np.array(names, dtype=str).reshape(-1),
        "intrinsics": K,
        "extrinsics": extrinsics,
        "bin_spec": np.array(json.dumps(TABLE_BIN, sort_keys=True)),
        "library_seed": np.array(-1, dtype=np.int64),
        "scene_seed": np.array(int(scene), dtype=np.int64),
        "split": np.array(split_of_scene(int(scene))),
        "layout": np.array(""),
        "object_set": np.array(""),
        "num_parcels": np.array(len(ids), dtype=np.int64),
        "rgb": rgb,
        "depth": depth,
        "segmentation": seg.astype(np.int16),
        "source": np.array(SOURCE),
        "suctionnet_root": np.array(str(Path(root).resolve())),
        "suctionnet_scene": np.array(int(scene), dtype=np.int64),
        "suctionnet_camera": np.array(camera),
        "suctionnet_ann_id": np.array(int(ann_id), dtype=np.int64),
        "depth_factor": np.array(factor, dtype=np.float64),
    }
    if sidecar is not None:
        for key in SIDECAR_PASSTHROUGH:
            if key in sidecar:
                record[key] = sidecar[key]
        if "object_com" in sidecar:  # the parcel's centre of mass, not the samples' centroid
            com = sidecar["object_com"].astype(np.float64).reshape(-1, 3)
            record["object_com_world"] = (np.einsum("mij,mj->mi", world_from_model[:, :3, :3], com)
                                          + world_from_model[:, :3, 3])
    return record
