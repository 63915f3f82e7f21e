"""The fixed parcel library: 100 training and 13 held-out test assets, as in the paper.

Asset ``i`` is generated from ``np.random.default_rng([seed, i])`` alone, so it is identical
whatever else is generated and in whatever order; the split and category of every index are fixed
by a round-robin, so the clusters are balanced. Assets are generated when first asked for and kept:
a 30-parcel pile pays for its 30 (about 3 ms each), not the library's 113 (a third of a second on a
2-core host, once per process). The library is cached per seed.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, overload

import numpy as np

from parcelpick_env.assets.generator import generate_parcel
from parcelpick_env.assets.parcel import CATEGORIES, Category, ParcelAsset, Split

OBJECT_SETS: tuple[str, ...] = ("rectangular", "planar", "cylindrical", "mixed")
SPLITS: tuple[str, ...] = ("train", "test")
NUM_TRAIN, NUM_TEST = 100, 13


@dataclass(frozen=True)
class AssetKey:
    """What the library knows of an asset before generating it: enough to choose and index it."""

    asset_id: str
    category: Category
    split: Split


class AssetView(Sequence[ParcelAsset]):
    """Some of a library's assets, in order, generated when indexed (``len``, ids and keys generate nothing)."""

    def __init__(self, library: "AssetLibrary", indices: Sequence[int]) -> None:
        self._library = library
        self._indices = tuple(indices)

    def __len__(self) -> int:
        return len(self._indices)

    @overload
    def __getitem__(self, item: int) -> ParcelAsset: ...

    @overload
    def __getitem__(self, item: slice) -> "AssetView": ...

    def __getitem__(self, item: int | slice) -> "ParcelAsset | AssetView":
        if isinstance(item, slice):
            return AssetView(self._library, self._indices[item])
        return self._library[self._indices[item]]

    def __add__(self, other: "AssetView") -> "AssetView":
        if not isinstance(other, AssetView) or other._library is not self._library:
            return NotImplemented
        return AssetView(self._library, self._indices + other._indices)

    @property
    def ids(self) -> list[str]:
        """The assets' ids, in order, without generating them."""
        return [self._library.keys[i].asset_id for i in self._indices]


class AssetLibrary:
    """Immutable collection of parcel assets with a train/test split and per-cluster views."""

    def __init__(self, assets: Sequence[ParcelAsset], seed: int | None = None) -> None:
        """A library of assets made elsewhere (``generate`` makes the project's, lazily)."""
        assets = list(assets)
        self._setup([AssetKey(a.asset_id, a.category, a.split) for a in assets], assets.__getitem__, seed)
        self._made.update(enumerate(assets))

    def _setup(self, keys: list[AssetKey], make: Callable[[int], ParcelAsset], seed: int | None) -> None:
        ids = [k.asset_id for k in keys]
        if len(set(ids)) != len(ids):
            raise ValueError("asset ids in a library must be unique")
        self.seed = seed
        self.keys: tuple[AssetKey, ...] = tuple(keys)
        self._index = {asset_id: i for i, asset_id in enumerate(ids)}
        self._make = make
        self._made: dict[int, ParcelAsset] = {}
        self._lock = threading.Lock()  # one asset object per index, whichever thread asks first
        self._recipe: tuple[int, int, int] | None = None  # (seed, num_train, num_test) of a generated library

    @classmethod
    def generate(cls, seed: int = 0, num_train: int = NUM_TRAIN, num_test: int = NUM_TEST) -> "AssetLibrary":
        """A fresh library, each asset generated on first use; categories cycle so each split is balanced."""
        if num_train < 0 or num_test < 0 or num_train + num_test == 0:
            raise ValueError(f"need a non-negative number of assets and at least one, got {num_train}/{num_test}")
        keys = []
        for index in range(num_train + num_test):
            split: Split = "train" if index < num_train else "test"
            k = index if split == "train" else index - num_train
            category = CATEGORIES[k % len(CATEGORIES)]
            keys.append(AssetKey(f"{split}-{category}-{k:03d}", category, split))

        def make(index: int) -> ParcelAsset:
            key = keys[index]
            return generate_parcel(key.category, np.random.default_rng([int(seed), index]), key.asset_id, key.split)

        library = cls.__new__(cls)
        library._setup(keys, make, seed)
        library._recipe = (int(seed), num_train, num_test)
        return library

    def __reduce__(self) -> tuple:
        """Pickled as its recipe where it has one (the assets regenerate identically), else as its assets."""
        if self._recipe is not None:
            return AssetLibrary.generate, self._recipe
        return AssetLibrary, ([self[i] for i in range(len(self))], self.seed)

    @staticmethod
    def default(seed: int = 0) -> "AssetLibrary":
        """The project's standard library (100 train + 13 test), one per process and seed."""
        return _default_library(int(seed))

    def __len__(self) -> int:
        return len(self.keys)

    def __getitem__(self, index: int) -> ParcelAsset:
        """The asset of generation index ``index`` (made now if it has not been)."""
        if not 0 <= index < len(self.keys):
            raise IndexError(f"asset index {index} is not in a library of {len(self.keys)} assets")
        asset = self._made.get(index)
        if asset is None:
            with self._lock:
                asset = self._made.get(index)
                if asset is None:
                    asset = self._made[index] = self._make(index)
        return asset

    def _view(self, split: str, object_set: str = "mixed") -> AssetView:
        return AssetView(self, [i for i, k in enumerate(self.keys)
                                if k.split == split and (object_set == "mixed" or k.category == object_set)])

    @property
    def train(self) -> AssetView:
        return self._view("train")

    @property
    def test(self) -> AssetView:
        return self._view("test")

    def assets(self, split: str, object_set: str = "mixed") -> AssetView:
        """Assets of one split, restricted to one cluster unless ``object_set`` is 'mixed'."""
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if object_set not in OBJECT_SETS:
            raise ValueError(f"object_set must be one of {OBJECT_SETS}, got {object_set!r}")
        return self._view(split, object_set)

    def get(self, asset_id: str) -> ParcelAsset:
        try:
            index = self._index[asset_id]
        except KeyError:
            raise KeyError(f"no asset {asset_id!r} in this library") from None
        return self[index]


@lru_cache(maxsize=4)
def _default_library(seed: int) -> AssetLibrary:
    return AssetLibrary.generate(seed)
