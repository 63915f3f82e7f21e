"""The parcel asset: one procedurally generated parcel, independent of any scene."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import trimesh

Category = Literal["rectangular", "planar", "cylindrical"]
CATEGORIES: tuple[Category, ...] = ("rectangular", "planar", "cylindrical")
Split = Literal["train", "test"]


@dataclass(frozen=True, eq=False)
class ParcelAsset:
    """A parcel as a rigid body.

    ``mesh`` is the true surface (dents, wrinkles) in the parcel's body frame, whose origin is the
    mesh's geometric centre. Scoring uses this mesh; simulation may collide with its convex hull.
    ``com`` is the centre of mass in the same frame, so an off-centre load is representable.
    """

    asset_id: str
    category: Category
    split: Split
    mesh: trimesh.Trimesh
    mass: float
    com: np.ndarray
    rgba: tuple[float, float, float, float]
    extents: np.ndarray = field(repr=False)
