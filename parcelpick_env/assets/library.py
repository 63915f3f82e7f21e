"""The fixed parcel library: 100 training and 13 held-out test assets, as in the paper.

Asset ``i`` is generated from ``np.random.default_rng([seed, i])`` alone, so it is identical
whatever else is generated and in whatever order; the split and category of every index are fixed
by a round-robin, so the clusters are balanced. The whole default library builds in well under a
second and is cached per seed.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from parcelpick_env.assets.generator import generate_parcel
from parcelpick_env.assets.parcel import CATEGORIES, ParcelAsset

OBJECT_SETS: tuple[str, ...] = ("rectangular", "planar", "cylindrical", "mixed")
SPLITS: tuple[str, ...] = ("train", "test")
NUM_TRAIN, NUM_TEST = 100, 13


class AssetLibrary:
    """Immutable collection of parcel assets with a train/test split and per-cluster views."""

    def __init__(self, assets: list[ParcelAsset], seed: int | None = None) -> None:
        ids = [a.asset_id for a in assets]
        if len(set(ids)) != len(ids):
            raise ValueError("asset ids in a library must be unique")
        self.seed = seed
        self._assets = list(assets)
        self._by_id = {a.asset_id: a for a in assets}

    @classmethod
    def generate(cls, seed: int = 0, num_train: int = NUM_TRAIN, num_test: int = NUM_TEST) -> "AssetLibrary":
        """Build a fresh library; categories cycle so each split is balanced across clusters."""
        if num_train < 0 or num_test < 0 or num_train + num_test == 0:
            raise ValueError(f"need a non-negative number of assets and at least one, got {num_train}/{num_test}")
        assets = []
        for index in range(num_train + num_test):
            split = "train" if index < num_train else "test"
            k = index if split == "train" else index - num_train
            category = CATEGORIES[k % len(CATEGORIES)]
            rng = np.random.default_rng([int(seed), index])
            assets.append(generate_parcel(category, rng, f"{split}-{category}-{k:03d}", split))
        return cls(assets, seed=seed)

    @staticmethod
    def default(seed: int = 0) -> "AssetLibrary":
        """The project's standard library (100 train + 13 test), generated once per process and seed."""
        return _default_library(int(seed))

    def __len__(self) -> int:
        return len(self._assets)

    @property
    def train(self) -> list[ParcelAsset]:
        return [a for a in self._assets if a.split == "train"]

    @property
    def test(self) -> list[ParcelAsset]:
        return [a for a in self._assets if a.split == "test"]

    def assets(self, split: str, object_set: str = "mixed") -> list[ParcelAsset]:
        """Assets of one split, restricted to one cluster unless ``object_set`` is 'mixed'."""
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if object_set not in OBJECT_SETS:
            raise ValueError(f"object_set must be one of {OBJECT_SETS}, got {object_set!r}")
        return [a for a in self._assets
                if a.split == split and (object_set == "mixed" or a.category == object_set)]

    def get(self, asset_id: str) -> ParcelAsset:
        try:
            return self._by_id[asset_id]
        except KeyError:
            raise KeyError(f"no asset {asset_id!r} in this library") from None


@lru_cache(maxsize=4)
def _default_library(seed: int) -> AssetLibrary:
    return AssetLibrary.generate(seed)
