"""The true pile of a stored scene, rebuilt from its record: what the evaluator re-scores candidates on, and what
training targets that need the whole parcel (not only its visible points) are computed from."""

from __future__ import annotations

import json
from typing import Sequence

import numpy as np

from dataset.storage import Record
from dataset.suctionnet.models import is_suctionnet_record
from dataset.suctionnet.models import world_meshes as suctionnet_world_meshes
from dataset.suctionnet.reader import ASSET_PREFIX as SUCTIONNET_ASSET_PREFIX
from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.assets.parcel import ParcelAsset
from parcelpick_env.scene.scene import BinSpec, ParcelState, Scene
from parcelpick_env.suction.geometry import surface_centroid

# What rebuilding the true pile reads from each stored scene (dataset/annotate.py writes them).
GROUND_TRUTH_KEYS = ("object_asset_ids", "object_categories", "object_poses", "bin_spec", "library_seed")


def require_keys(record: Record, keys: Sequence[str], where: str) -> None:
    missing = [k for k in keys if k not in record]
    if missing:
        hint = "; regenerate the dataset with images (without --no-images)" if {"rgb", "depth"} & set(missing) else ""
        raise ValueError(f"{where} lacks {missing}{hint}")


def scene_from_record(record: Record, library: AssetLibrary | None = None) -> Scene:
    """The true pile of a stored scene: library meshes placed at the stored poses, and the bin. A view read from a
    SuctionNet-1Billion tree (``dataset.suctionnet``) brings its own object models instead."""
    asset_ids = np.asarray(record.get("object_asset_ids", [])).reshape(-1)
    if is_suctionnet_record(record) and len(asset_ids) and str(asset_ids[0]).startswith(SUCTIONNET_ASSET_PREFIX):
        parcels = _suctionnet_parcels(record)
    else:
        require_keys(record, GROUND_TRUTH_KEYS, "scene record")
        if library is None:
            library = AssetLibrary.default(int(record["library_seed"]))
        poses = np.asarray(record["object_poses"], dtype=np.float64).reshape(-1, 7)
        if len(asset_ids) != len(poses):
            raise ValueError(f"scene record has {len(asset_ids)} asset ids but {len(poses)} poses")
        parcels = [ParcelState(object_id=k, body_id=-1, asset=library.get(str(asset_id)), position=pose[:3],
                               orientation=pose[3:], friction=float("nan"))
                   for k, (asset_id, pose) in enumerate(zip(asset_ids, poses))]
    return Scene(parcels=parcels, bin=bin_from_record(record), seed=int(record.get("scene_seed", -1)),
                 layout=str(record.get("layout", "")), object_set=str(record.get("object_set", "")),
                 split=str(record.get("split", "")))


def _suctionnet_parcels(record: Record) -> list[ParcelState]:
    """SuctionNet's objects, which the asset library does not hold: each posed model is an asset at the identity
    pose, with a unit mass at its surface centroid (SuctionNet has no masses: only the ``suctionnet`` and
    ``paper_compat`` definitions apply to such scenes)."""
    parcels = []
    for k, (asset_id, mesh) in enumerate(zip(np.asarray(record["object_asset_ids"]).reshape(-1),
                                             suctionnet_world_meshes(record))):
        centroid = surface_centroid(mesh)
        asset = ParcelAsset(asset_id=str(asset_id), category="suctionnet", split="test", mesh=mesh, mass=1.0,  # type: ignore[arg-type]
                            com=centroid, rgba=(1.0, 1.0, 1.0, 1.0), extents=np.asarray(mesh.extents))
        parcels.append(ParcelState(object_id=k, body_id=-1, asset=asset, position=np.zeros(3),
                                   orientation=np.array([0.0, 0.0, 0.0, 1.0]), friction=float("nan")))
    return parcels


def bin_from_record(record: Record) -> BinSpec:
    bin_fields = json.loads(str(record["bin_spec"]))
    return BinSpec(**{k: tuple(v) if isinstance(v, list) else v for k, v in bin_fields.items()})
