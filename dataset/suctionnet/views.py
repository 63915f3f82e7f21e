"""A GraspNet/SuctionNet tree served as a ParcelPick dataset, read view by view: the one place that decides
what ``--data DIR`` is, for the torch Dataset and every trainer.

``open_store(path)`` returns ``dataset.storage.open_dataset(path)`` for a ParcelPick dataset directory, and a
``SuctionNetViews`` over the ``train`` split (scenes 0-99) of every camera present for a SuctionNet root. Both
answer the same calls (``len``, ``scene(i, keys)``, ``config``, ``scene_indices``, ``close``), so
``ParcelSuctionDataset`` and the Cao and Dex-Net trainers take either unchanged.

Views are read on demand by ``reader.read_view`` rather than imported to shards first: the records are the ones
``python -m dataset.suctionnet import`` stores (the same reader), nothing is written into the user's tree or a
hidden cache, and the Cao and Dex-Net trainers read each view once anyway. A Diffusion-Suction run reads every
view again each epoch (2-3 s a 1280x720 view on one core), so for long runs import once
(``python -m dataset.suctionnet import ... --no-images``) and pass the imported directory instead
(docs/suctionnet_layout.md, "Training").
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from dataset.storage import Record, open_dataset
from dataset.suctionnet.convert import split_views
from dataset.suctionnet.layout import CAMERAS, SPLITS, SuctionNetLayoutError, check_label_dirs, is_suctionnet_root
from dataset.suctionnet.reader import LABEL_SET, SOURCE, ReaderConfig, read_view

TRAIN_SPLIT = "train"


class SuctionNetViews:
    """``views`` ((camera, scene, ann_id) triples) of a SuctionNet root, each read as a record when asked for."""

    def __init__(self, root: str | os.PathLike, views: Sequence[tuple[str, int, int]], split: str,
                 reader: ReaderConfig = ReaderConfig()) -> None:
        if not views:
            raise ValueError(f"{root}: no views to serve")
        self.root = Path(root)
        self.views = [(str(c), int(s), int(a)) for c, s, a in views]
        self.reader = reader
        self.config: dict[str, Any] = {
            "source": SOURCE, "graspnet_root": str(self.root.resolve()), "split": split, "labels": LABEL_SET,
            "cameras": sorted({c for c, _, _ in self.views}), "views": [list(v) for v in self.views],
            "reader": dataclasses.asdict(reader), "scenes": len(self.views)}
        self.scene_indices = list(range(len(self.views)))

    def __len__(self) -> int:
        return len(self.views)

    def scene(self, i: int, keys: Iterable[str] | None = None) -> Record:
        """The record of the ``i``-th view (all keys, or only ``keys``), as ``ShardedDataset.scene``."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"view {i} out of range for {len(self)} views")
        camera, scene, ann_id = self.views[i % len(self)]
        record = read_view(self.root, scene, camera, ann_id, self.reader)
        if keys is None:
            return record
        keys = list(keys)
        missing = [key for key in keys if key not in record]
        if missing:
            raise KeyError(f"{self.root} scene {scene} {camera} view {ann_id} has no {missing}")
        return {key: record[key] for key in keys}

    def close(self) -> None:
        """Nothing is held open (the reader's label caches are per process)."""


def suctionnet_views(root: str | os.PathLike, split: str = TRAIN_SPLIT, cameras: Sequence[str] | None = None,
                     reader: ReaderConfig = ReaderConfig()) -> SuctionNetViews:
    """Every view of ``split`` under ``root`` for ``cameras`` (default: each camera with views there), camera by
    camera; one clear error for a tree without SuctionNet's labels or without any view of the split."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {sorted(SPLITS)}, got {split!r}")
    check_label_dirs(root)
    views: list[tuple[str, int, int]] = []
    for camera in cameras or CAMERAS:
        try:
            views += [(camera, s, a) for s, a in split_views(root, camera, split)]
        except SuctionNetLayoutError:
            if cameras:  # asked for by name: its absence is the error
                raise
    if not views:
        raise SuctionNetLayoutError(f"{Path(root) / 'scenes'}: no views of split {split} (scenes "
                                    f"{SPLITS[split].start}-{SPLITS[split].stop - 1}) for any of {list(CAMERAS)}")
    return SuctionNetViews(root, views, split, reader)


def open_store(path: str | os.PathLike, **open_kwargs: Any) -> Any:
    """A ParcelPick dataset directory (``open_dataset(path, **open_kwargs)``) or, for a SuctionNet root, its
    training views (``suctionnet_views``; ``open_kwargs`` concern shards and are ignored there)."""
    if is_suctionnet_root(path):
        return suctionnet_views(path)
    return open_dataset(path, **open_kwargs)


def store_config(path: str | os.PathLike) -> dict[str, Any]:
    """What a dataset directory's manifest records, or what a SuctionNet root's views are (for provenance)."""
    store = open_store(path)
    try:
        return dict(store.config)
    finally:
        store.close()
