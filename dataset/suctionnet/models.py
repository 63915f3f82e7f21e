"""The true object surfaces of a SuctionNet-layout record, for an evaluator that re-scores on them.

``eval/ap.py`` rebuilds parcels from the procedural asset library (``object_asset_ids``, ``library_seed``);
SuctionNet objects are not in it. A record read by ``dataset.suctionnet.reader`` instead names its
dataset root (``suctionnet_root``), its models (``object_model_ids``: ``models/XXX/nontextured.ply``,
``dense_point_clouds/XXX.npz``) and their world poses (``object_poses``), which is all these need.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from dataset.storage import Record
from dataset.suctionnet.layout import Layout, SuctionNetLayoutError, load_npz

MODEL_KEYS = ("suctionnet_root", "object_model_ids", "object_poses")


def is_suctionnet_record(record: Record) -> bool:
    """Whether ``record`` names SuctionNet models (so its meshes come from here, not the asset library)."""
    return all(key in record for key in MODEL_KEYS)


@functools.lru_cache(maxsize=128)
def _model(root: str, obj_id: int) -> trimesh.Trimesh:
    path = Layout(root).model_mesh(obj_id)
    if not path.is_file():
        raise SuctionNetLayoutError(f"{path}: model of object {obj_id} is missing")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for a damaged PLY
        raise SuctionNetLayoutError(f"{path}: not a readable triangle mesh ({exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise SuctionNetLayoutError(f"{path}: holds no triangles")
    return mesh


def _world_from_model(record: Record) -> tuple[str, np.ndarray, np.ndarray]:
    missing = [key for key in MODEL_KEYS if key not in record]
    if missing:
        raise ValueError(f"record lacks {missing}: it was not read from a SuctionNet-layout tree")
    ids = np.asarray(record["object_model_ids"]).reshape(-1).astype(np.int64)
    poses = np.asarray(record["object_poses"], dtype=np.float64).reshape(-1, 7)
    if len(ids) != len(poses):
        raise ValueError(f"record has {len(ids)} model ids but {len(poses)} poses")
    T = np.tile(np.eye(4), (len(ids), 1, 1))
    if len(ids):
        T[:, :3, :3] = Rotation.from_quat(poses[:, 3:]).as_matrix()
        T[:, :3, 3] = poses[:, :3]
    return str(np.asarray(record["suctionnet_root"])), ids, T


def world_meshes(record: Record) -> list[trimesh.Trimesh]:
    """Each object's ``nontextured.ply`` placed at its pose, in the record's world (table) frame."""
    root, ids, T = _world_from_model(record)
    return [_model(root, int(i)).copy().apply_transform(T[k]) for k, i in enumerate(ids)]


def world_dense_points(record: Record) -> list[np.ndarray]:
    """Each object's dense surface sample (what suctionnetAPI's seal and wrench scores use), posed."""
    root, ids, T = _world_from_model(record)
    layout = Layout(root)
    out = []
    for k, i in enumerate(ids):
        points = load_npz(layout.dense_points(int(i)), f"dense point cloud of object {int(i)}", ("points",))["points"]
        out.append(np.asarray(points, dtype=np.float64) @ T[k, :3, :3].T + T[k, :3, 3])
    return out


def model_path(record: Record, k: int) -> Path:
    """The ``nontextured.ply`` of the record's ``k``-th object."""
    root, ids, _ = _world_from_model(record)
    return Layout(root).model_mesh(int(ids[k]))
