"""PyTorch view of a generated dataset: one scene's labelled point cloud per item.

HDF5 files are opened lazily inside each DataLoader worker (see ``ShardedDataset``) and only the
four arrays a model needs are read, so the dataset object is cheap to pickle to workers. A GraspNet/SuctionNet
root is served too, view by view (``dataset.suctionnet.views.open_store`` decides which a path is).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from dataset.suctionnet.views import open_store

ITEM_KEYS = ("points", "normals", "labels", "object_ids")


def label_key(config: dict[str, Any], label_set: str | None, root: str | os.PathLike = "dataset") -> tuple[str, str]:
    """(label set, stored key) for ``label_set`` in a dataset made with ``config`` (its manifest's): ``labels`` for
    the main set, ``labels_<set>`` for one stored beside it; one clear error naming what the dataset holds."""
    main = str(config.get("labels", "paper"))  # datasets made before label sets hold the paper's
    extras = [str(name) for name in config.get("extra_labels", [])]
    if label_set is None or label_set == main:
        return main, "labels"
    if label_set in extras:
        return label_set, f"labels_{label_set}"
    raise ValueError(f"{root} holds the label sets {[main, *extras]}, not {label_set!r} "
                     "(python -m dataset.generate --labels / --extra-labels)")


class ParcelSuctionDataset(Dataset):
    """Items are dicts: ``points`` (N,3) float32, ``normals`` (N,3) float32, ``labels`` (N,4) float32
    [seal, wrench, collision, visibility], ``object_ids`` (N,) int64, plus ``index`` (the item index).

    ``split`` (if given) must match the split the directory was generated for. ``num_points`` takes a
    random subset of that size per item (without replacement; padding by repetition if the scene has
    fewer). ``augment`` rotates the scene about the vertical axis (which leaves every label, including
    the gravity-dependent wrench, unchanged) and jitters points by ``jitter_std`` metres.
    Randomness is drawn from ``(seed, epoch, index)`` so an epoch is reproducible; call
    ``set_epoch`` to vary it between epochs. ``verify`` (default) checks every array read against its stored
    digest (``dataset.storage``); ``verify_checksums`` also checksums every shard up front. ``label_set`` serves
    one of the stored label sets (docs/labels.md, "Label sets") as ``labels``: the main one (None, the default) or
    one stored beside it with ``--extra-labels``.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        split: str | None = None,
        num_points: int | None = None,
        augment: bool = False,
        jitter_std: float = 0.001,
        shuffle_points: bool = False,
        transform: Callable[[dict[str, torch.Tensor]], dict[str, Any]] | None = None,
        seed: int = 0,
        verify_checksums: bool = False,
        verify: bool = True,
        label_set: str | None = None,
    ) -> None:
        if num_points is not None and (not isinstance(num_points, int) or num_points < 1):
            raise ValueError(f"num_points must be a positive integer or None, got {num_points!r}")
        if not np.isfinite(jitter_std) or jitter_std < 0:
            raise ValueError(f"jitter_std must be >= 0, got {jitter_std}")
        if seed < 0:
            raise ValueError(f"seed must be >= 0, got {seed}")
        self.store = open_store(root, verify=verify, checksum=verify_checksums)
        stored_split = self.store.config["split"]
        if split is not None and split != stored_split:
            raise ValueError(f"{root} holds the {stored_split!r} split, not {split!r}")
        self.split = stored_split
        self.label_set, self.label_key = label_key(self.store.config, label_set, root)
        self.num_points = num_points
        self.augment = augment
        self.jitter_std = float(jitter_std)
        self.shuffle_points = shuffle_points
        self.transform = transform
        self.seed = int(seed)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.store)

    def __getitem__(self, index: int) -> dict[str, Any]:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} scenes")
        index = index % len(self)
        keys = tuple(self.label_key if key == "labels" else key for key in ITEM_KEYS)
        arrays = self.store.scene(index, keys)
        points = arrays["points"].astype(np.float32)
        normals = arrays["normals"].astype(np.float32)
        labels = arrays[self.label_key].astype(np.float32)
        object_ids = arrays["object_ids"].astype(np.int64)
        rng = np.random.default_rng([self.seed, self.epoch, index])
        n = len(points)
        order = None
        if self.num_points is not None and self.num_points != n:
            order = rng.choice(n, size=self.num_points, replace=self.num_points > n)
        if self.shuffle_points:
            order = rng.permutation(n if order is None else order)
        if order is not None:
            points, normals, labels, object_ids = points[order], normals[order], labels[order], object_ids[order]
        if self.augment:
            angle = rng.uniform(0.0, 2.0 * np.pi)
            c, s = np.cos(angle), np.sin(angle)
            rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float32)
            points = points @ rot.T
            normals = normals @ rot.T
            if self.jitter_std > 0:
                points = points + rng.normal(0.0, self.jitter_std, size=points.shape).astype(np.float32)
        item: dict[str, Any] = {
            "points": torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32)),
            "normals": torch.from_numpy(np.ascontiguousarray(normals, dtype=np.float32)),
            "labels": torch.from_numpy(np.ascontiguousarray(labels, dtype=np.float32)),
            "object_ids": torch.from_numpy(np.ascontiguousarray(object_ids, dtype=np.int64)),
            "index": index,
        }
        return self.transform(item) if self.transform is not None else item
