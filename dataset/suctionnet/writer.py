"""ParcelPick records -> the GraspNet/SuctionNet layout, so a miniature SuctionNet-format dataset can be
made here, read back by ``dataset.suctionnet.reader`` and handed to SuctionNet's own tools.

Each record becomes one scene with one view (annotation id 0) of one camera. The world frame is
written as SuctionNet's table frame (``cam0_wrt_table.npy`` = the record's camera-to-world
``extrinsics``, ``camera_poses.npy`` = identity), which is exact: both are z up with gravity -z.

SuctionNet labels live on object models, shared across scenes; ParcelPick's live on the captured
points of one scene. So every parcel *instance* becomes its own SuctionNet object (model id), whose
seal samples are that scene's labelled points on it, carried into the model frame, with their seal
scores; the scene's wrench and collision files hold the same points' wrench scores and collision flags.
Reading a view back therefore finds, for each point, its own sample, and returns its own labels.
What the layout cannot hold (sampled pixels, camera normals, visibility, asset ids, masses, the bin,
seeds) goes into a sidecar, ``<camera>/parcelpick/0000.npz``, that SuctionNet's tools never open.
"""

from __future__ import annotations

import itertools
import json
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from dataset.storage import Record
from dataset.suctionnet.layout import LABEL_OFFSET, Layout, write_annotation, write_png
from dataset.suctionnet.reader import SIDECAR_PASSTHROUGH

ANN_ID = 0  # ParcelPick stores one view per scene
WRITE_KEYS = ("rgb", "depth", "segmentation", "intrinsics", "extrinsics", "points", "normals", "labels",
              "object_ids", "point_pixels", "object_poses", "object_asset_ids", "library_seed")


@dataclass(frozen=True)
class WriterConfig:
    """``camera`` must be 'kinect' or 'realsense' for suctionnetAPI to accept the tree."""

    camera: str = "realsense"
    depth_factor: float = 1000.0  # GraspNet's: depth PNG in millimetres
    dense_spacing: float = 0.002  # m between dense surface samples (suctionnetAPI's own are 0.2 mm)
    max_dense_points: int = 200_000

    def __post_init__(self) -> None:
        if not self.camera or "/" in self.camera:
            raise ValueError(f"WriterConfig.camera must be a directory name, got {self.camera!r}")
        if not self.depth_factor > 0:
            raise ValueError(f"WriterConfig.depth_factor must be > 0, got {self.depth_factor!r}")
        if not self.dense_spacing > 0 or self.max_dense_points < 1:
            raise ValueError("WriterConfig.dense_spacing must be > 0 and max_dense_points >= 1")


def _world_from_model(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 7)
    T = np.tile(np.eye(4), (len(poses), 1, 1))
    if len(poses):
        T[:, :3, :3] = Rotation.from_quat(poses[:, 3:]).as_matrix()
        T[:, :3, 3] = poses[:, :3]
    return T


def _check(record: Record, index: int) -> None:
    missing = [key for key in WRITE_KEYS if key not in record]
    if missing:
        hint = " (generate with images: without --no-images)" if {"rgb", "depth", "segmentation"} & set(missing) else ""
        raise ValueError(f"record {index} lacks {missing}{hint}")


def _write_model(layout: Layout, model_id: int, mesh: Any, config: WriterConfig) -> None:
    import open3d as o3d

    path = layout.model_mesh(model_id)
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(path)
    o3d_mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=np.float64)),
                                         o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)))
    count = int(np.clip(np.ceil(mesh.area / config.dense_spacing ** 2), 1, config.max_dense_points))
    dense = o3d_mesh.sample_points_uniformly(number_of_points=count, use_triangle_normal=True)
    dense_path = layout.dense_points(model_id)
    dense_path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(dense_path, allow_pickle=False, points=np.asarray(dense.points, dtype=np.float32),
             normals=np.asarray(dense.normals, dtype=np.float32))


def write_scene(record: Record, root: str | os.PathLike, scene: int, first_model_id: int,
                config: WriterConfig = WriterConfig(), library: Any = None) -> list[int]:
    """Write one record as scene ``scene`` (view 0); its parcels become models ``first_model_id ...``.

    Returns the model ids used, in the record's object order.
    """
    import scipy.io

    from parcelpick_env.assets.library import AssetLibrary

    layout, camera = Layout(root), config.camera
    if layout.camera_dir(scene, camera).exists():
        raise FileExistsError(f"{layout.camera_dir(scene, camera)} already exists; write to a new root")
    asset_ids = np.asarray(record["object_asset_ids"]).reshape(-1).astype(str)
    world_from_model = _world_from_model(record["object_poses"])
    if len(asset_ids) != len(world_from_model):
        raise ValueError(f"scene {scene}: {len(asset_ids)} asset ids but {len(world_from_model)} poses")
    model_ids = list(range(first_model_id, first_model_id + len(asset_ids)))
    if model_ids and model_ids[-1] > 999:
        raise ValueError(f"scene {scene}: model id {model_ids[-1]} does not fit SuctionNet's 3-digit names")
    library = library if library is not None else AssetLibrary.default(int(record["library_seed"]))

    extrinsics = np.asarray(record["extrinsics"], dtype=np.float64)
    K = np.asarray(record["intrinsics"], dtype=np.float64)
    cam_from_world = np.linalg.inv(extrinsics)
    cam_from_model = cam_from_world[None] @ world_from_model

    depth = np.asarray(record["depth"], dtype=np.float64)
    raw = np.rint(depth * config.depth_factor)
    if raw.max(initial=0) > np.iinfo(np.uint16).max:
        raise ValueError(f"scene {scene}: depth {depth.max():.2f} m overflows a 16-bit PNG "
                         f"at factor {config.depth_factor}")
    seg = np.asarray(record["segmentation"], dtype=np.int64)
    ids = np.asarray(model_ids, dtype=np.int64)
    label = np.where(seg >= 0, ids[np.clip(seg, 0, max(len(ids) - 1, 0))] + LABEL_OFFSET if len(ids) else 0, 0)
    write_png(layout.view_file(scene, camera, "rgb", ANN_ID), np.asarray(record["rgb"], dtype=np.uint8))
    write_png(layout.view_file(scene, camera, "depth", ANN_ID), raw.astype(np.uint16))
    write_png(layout.view_file(scene, camera, "label", ANN_ID),
              label.astype(np.uint8 if label.max(initial=0) < 256 else np.uint16))

    meta_path = layout.view_file(scene, camera, "meta", ANN_ID)
    meta_path.parent.mkdir(parents=True, exist_ok=True)
    scipy.io.savemat(str(meta_path), {
        "intrinsic_matrix": K, "factor_depth": np.array([[config.depth_factor]]),
        "cls_indexes": (ids + LABEL_OFFSET).reshape(1, -1).astype(np.float64),
        "poses": np.transpose(cam_from_model[:, :3, :], (1, 2, 0)) if len(ids) else np.zeros((3, 4, 0)),
    })
    quat_wxyz = np.roll(Rotation.from_matrix(cam_from_model[:, :3, :3]).as_quat(), 1, axis=1) if len(ids) else []
    write_annotation(layout.view_file(scene, camera, "annotations", ANN_ID),
                     [(m, name, str(layout.model_mesh(m).parent), cam_from_model[k, :3, 3], quat_wxyz[k])
                      for k, (m, name) in enumerate(zip(model_ids, asset_ids))])
    cam_dir = layout.camera_dir(scene, camera)
    np.save(cam_dir / "camK.npy", K)
    np.save(cam_dir / "camera_poses.npy", np.eye(4)[None])
    np.save(cam_dir / "cam0_wrt_table.npy", extrinsics)
    np.save(layout.scene_dir(scene) / "rs_wrt_kn.npy", np.eye(4))
    layout.object_id_list(scene).write_text("".join(f"{m}\n" for m in model_ids))

    points = np.asarray(record["points"], dtype=np.float64)
    normals = np.asarray(record["normals"], dtype=np.float64)
    labels = np.asarray(record["labels"], dtype=np.float64)
    object_ids = np.asarray(record["object_ids"]).reshape(-1)
    wrenches, collisions = [], []
    for k, model_id in enumerate(model_ids):
        on = object_ids == k
        R, t = world_from_model[k, :3, :3], world_from_model[k, :3, 3]
        seal_path = layout.seal_label(model_id)
        seal_path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(seal_path, allow_pickle=False, points=((points[on] - t) @ R).astype(np.float32),
                 normals=(normals[on] @ R).astype(np.float32),
                 scores=labels[on, 0].astype(np.float32), collision=np.zeros(int(on.sum()), dtype=bool))
        wrenches.append(labels[on, 1].astype(np.float32))
        collisions.append(labels[on, 2] < 0.5)
        _write_model(layout, model_id, library.get(str(asset_ids[k])).mesh, config)
    for path, arrays in ((layout.wrench_label(scene), wrenches), (layout.collision_label(scene), collisions)):
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, *arrays, allow_pickle=False)

    sidecar = {key: np.asarray(record[key]) for key in SIDECAR_PASSTHROUGH if key in record}
    sidecar.update(point_pixels=np.asarray(record["point_pixels"], dtype=np.int32),
                   normals=(normals @ extrinsics[:3, :3]).astype(np.float32))
    sidecar_path = layout.view_file(scene, camera, "parcelpick", ANN_ID)
    sidecar_path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(sidecar_path, allow_pickle=False, **sidecar)
    return model_ids


def write_records(records: Iterable[Record], root: str | os.PathLike, scenes: Sequence[int] | None = None,
                  config: WriterConfig = WriterConfig()) -> dict[int, list[int]]:
    """Write ``records`` as scenes ``scenes`` (default 0, 1, ...) of a new tree at ``root``; returns
    {scene: model ids}. Records are written one at a time, so ``records`` may be a generator.

    A ``parcelpick_objects.json`` at the root maps every model id to its scene and ParcelPick asset id.
    """
    if scenes is None:
        records = list(records)
        scenes = range(len(records))
    scenes = [int(s) for s in scenes]
    if len(set(scenes)) != len(scenes) or any(not 0 <= s <= 9999 for s in scenes):
        raise ValueError(f"scene ids must be distinct and in [0, 9999], got {scenes}")
    root = Path(root)
    if root.exists() and any(root.iterdir()):  # model ids restart at 000: never mix with another tree's objects
        raise FileExistsError(f"{root} is not empty; write a SuctionNet tree to a new directory")
    written: dict[int, list[int]] = {}
    objects: dict[str, Any] = {}
    next_id = 0
    count = 0
    for count, (scene, record) in enumerate(itertools.zip_longest(scenes, records), start=1):
        if scene is None or record is None:
            raise ValueError(f"got {'more' if scene is None else 'fewer'} records than the {len(scenes)} scene ids")
        _check(record, count - 1)
        root.mkdir(parents=True, exist_ok=True)
        ids = write_scene(record, root, scene, next_id, config)
        written[scene] = ids
        for k, model_id in enumerate(ids):
            objects[f"{model_id:03d}"] = {"scene": scene, "object": k,
                                          "asset_id": str(np.asarray(record["object_asset_ids"]).reshape(-1)[k])}
        next_id += len(ids)
    if count == 0:
        raise ValueError("no records to write")
    (root / "parcelpick_objects.json").write_text(json.dumps({"camera": config.camera, "objects": objects},
                                                             indent=2, sort_keys=True))
    return written


def export_dataset(data_dir: str | os.PathLike, root: str | os.PathLike, scenes: int | None = None,
                   first_scene: int = 0, config: WriterConfig = WriterConfig()) -> dict[int, list[int]]:
    """The first ``scenes`` scenes (all by default) of a ParcelPick dataset directory, as scenes
    ``first_scene ...`` of a SuctionNet tree (e.g. 100 to land in SuctionNet's test_seen range)."""
    from dataset.storage import open_dataset

    store = open_dataset(data_dir)
    try:
        count = len(store) if scenes is None else min(int(scenes), len(store))
        return write_records((store.scene(i) for i in range(count)), root,
                             range(first_scene, first_scene + count), config)
    finally:
        store.close()
