"""Hand-placed scenes with known answers (tests, demos): specific boxes at specific poses.

Use as ``EnvConfig(scene_factory=BoxScene([...]))`` or ``env.reset(options={'scene_factory': ...})``.
The factory resets the simulator, adds the bin and the parcels, settles them and returns a ``Scene``
with ``object_id == index`` as ``build_pile`` does.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import trimesh

from parcelpick_env.assets.parcel import ParcelAsset
from parcelpick_env.scene.scene import BinSpec, ParcelState, Scene
from parcelpick_env.sim.simulator import Simulator


def box_asset(extents: Sequence[float], mass: float, com: Sequence[float] = (0.0, 0.0, 0.0),
              asset_id: str | None = None, rgba=(0.75, 0.6, 0.4, 1.0)) -> ParcelAsset:
    """A rectangular carton of the given size (m) and mass (kg)."""
    extents = np.asarray(extents, dtype=np.float64)
    if extents.shape != (3,) or np.any(extents <= 0) or not mass > 0:
        raise ValueError(f"a box needs 3 positive extents and a positive mass, got {extents}, {mass}")
    mesh = trimesh.creation.box(extents=extents)
    mesh.visual.face_colors = (np.asarray(rgba) * 255).astype(np.uint8)
    name = asset_id or "box-{:.3f}x{:.3f}x{:.3f}-{:.2f}kg".format(*extents, mass)
    return ParcelAsset(asset_id=name, category="rectangular", split="test", mesh=mesh, mass=float(mass),
                       com=np.asarray(com, dtype=np.float64), rgba=tuple(rgba), extents=extents)


@dataclass(frozen=True)
class PlacedBox:
    extents: tuple[float, float, float]
    mass: float
    xy: tuple[float, float] = (0.0, 0.0)
    yaw: float = 0.0
    z: float | None = None  # bottom face height; None rests it on the bin floor
    friction: float = 0.6
    rgba: tuple[float, float, float, float] = (0.75, 0.6, 0.4, 1.0)


@dataclass(frozen=True)
class BoxScene:
    """A callable scene factory ``(sim, seed) -> Scene`` placing ``boxes`` flat in the bin."""

    boxes: Sequence[PlacedBox]
    bin: BinSpec = field(default_factory=BinSpec)
    settle_steps: int = 240

    def __call__(self, sim: Simulator, seed: int) -> Scene:
        from scipy.spatial.transform import Rotation

        sim.reset()
        sim.add_bin(self.bin)
        parcels: list[ParcelState] = []
        for i, b in enumerate(self.boxes):
            asset = box_asset(b.extents, b.mass, asset_id=f"placed-{i}", rgba=b.rgba)
            z = self.bin.floor_z if b.z is None else b.z
            pos = np.array([b.xy[0], b.xy[1], z + b.extents[2] / 2])
            orn = Rotation.from_euler("z", b.yaw).as_quat()
            body = sim.add_parcel(asset, pos, orn, b.friction)
            parcels.append(ParcelState(i, body, asset, pos, orn, b.friction))
        sim.settle([ps.body_id for ps in parcels], max_steps=self.settle_steps)
        for ps in parcels:
            ps.position, ps.orientation = sim.body_pose(ps.body_id)
        return Scene(parcels=parcels, bin=self.bin, seed=int(seed), layout="scattered",
                     object_set="rectangular", split="test", meta={"factory": "BoxScene"})
