"""SuctionNet views -> a ParcelPick dataset directory (HDF5 shards), so the torch Dataset, the trainers
and ``eval/ap.py`` open it as they open a generated one (``dataset.storage.open_dataset``).

Each view is one stored scene, in the order scene by scene, annotation id by annotation id. The manifest's
``config`` records where the views came from (``source``, ``graspnet_root``, ``camera``, ``views``) and
the ``ReaderConfig`` that made the points and labels, as a generated dataset's records its
``GenerationConfig``.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from dataset.storage import read_manifest, shard_name, write_manifest, write_shard
from dataset.suctionnet.layout import SPLITS, SuctionNetLayoutError
from dataset.suctionnet.reader import LABEL_SET, SOURCE, ReaderConfig, read_view

IMAGE_KEYS = ("rgb", "depth", "segmentation")  # dropped with images=False, as generate's --no-images


def import_views(graspnet_root: str | os.PathLike, out: str | os.PathLike, camera: str,
                 views: Sequence[tuple[int, int]], split: str = "custom", config: ReaderConfig = ReaderConfig(),
                 scenes_per_shard: int = 100, images: bool = True,
                 progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Read ``views`` ((scene, ann_id) pairs) of ``camera`` and store them as ``out``; returns the manifest.

    ``out`` must not hold a dataset already. A bad file stops the run with ``SuctionNetLayoutError`` naming it.
    """
    out = Path(out)
    if (out / "manifest.json").exists():
        raise FileExistsError(f"{out} already holds a dataset ({read_manifest(out)['num_scenes']} scenes)")
    if not views:
        raise ValueError("no views to import")
    if scenes_per_shard < 1:
        raise ValueError(f"scenes_per_shard must be >= 1, got {scenes_per_shard}")
    out.mkdir(parents=True, exist_ok=True)
    manifest_config = {"source": SOURCE, "graspnet_root": str(Path(graspnet_root).resolve()), "camera": camera,
                       "views": [[int(s), int(a)] for s, a in views], "split": split, "labels": LABEL_SET,
                       "reader": dataclasses.asdict(config), "scenes": len(views),
                       "scenes_per_shard": scenes_per_shard, "store_images": images}
    shards = []
    for shard, start in enumerate(range(0, len(views), scenes_per_shard)):
        indices = range(start, min(start + scenes_per_shard, len(views)))
        records = {}
        for i in indices:
            record = read_view(graspnet_root, views[i][0], camera, views[i][1], config)
            records[i] = {k: v for k, v in record.items() if images or k not in IMAGE_KEYS}
            if progress is not None:
                progress(i + 1, len(views))
        shards.append(write_shard(out / shard_name(shard), shard, records, indices))
        write_manifest(out, manifest_config, shards, complete=False)
    return write_manifest(out, manifest_config, shards, complete=True)


def split_views(graspnet_root: str | os.PathLike, camera: str, split: str,
                ann_ids: Sequence[int] | None = None) -> list[tuple[int, int]]:
    """(scene, ann_id) for every scene of a public split present under ``graspnet_root`` and every
    annotation id (all meta files found, unless ``ann_ids``); a split with no scene present is an error."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {sorted(SPLITS)}, got {split!r}")
    root = Path(graspnet_root)
    views = []
    for scene in SPLITS[split]:
        meta_dir = root / "scenes" / f"scene_{scene:04d}" / camera / "meta"
        if not meta_dir.is_dir():
            continue
        found = sorted(int(p.stem) for p in meta_dir.glob("[0-9][0-9][0-9][0-9].mat"))
        views += [(scene, a) for a in (found if ann_ids is None else [a for a in ann_ids if a in found])]
    if not views:
        raise SuctionNetLayoutError(f"{root / 'scenes'}: no {camera} views of split {split} "
                                    f"(scenes {SPLITS[split].start}-{SPLITS[split].stop - 1})")
    return views
