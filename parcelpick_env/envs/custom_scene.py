"""Hand-placed scenes with known answers (tests, demos): specific boxes at specific poses.

Use as ``EnvConfig(scene_factory=BoxScene([...]))`` or ``env.reset(options={'scene_factory': ...})``.
The factory resets the simulator, adds the bin, any static ``fixtures`` (a tilted slab to rest a
parcel on, a bar to strike), and the parcels, settles them and returns a ``Scene`` with
``object_id == index`` as ``build_pile`` does; the fixtures' body ids are in ``scene.meta['fixtures']``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import pybullet as pb
import trimesh
from scipy.spatial.transform import Rotation

from parcelpick_env.assets.parcel import ParcelAsset
from parcelpick_env.scene.scene import BinSpec, ParcelState, Scene
from parcelpick_env.sim.simulator import Simulator


def box_asset(extents: Sequence[float], mass: float, com: Sequence[float] = (0.0, 0.0, 0.0),
              asset_id: str | None = None, rgba=(0.75, 0.6, 0.4, 1.0)) -> ParcelAsset:
    """A rectangular carton of the given size (m) and mass (kg)."""
    size = np.asarray(extents, dtype=np.float64)
    if size.shape != (3,) or np.any(size <= 0) or not mass > 0:
        raise ValueError(f"a box needs 3 positive extents and a positive mass, got {size}, {mass}")
    mesh = trimesh.creation.box(extents=size)
    mesh.visual.face_colors = (np.asarray(rgba) * 255).astype(np.uint8)
    name = asset_id or "box-{:.3f}x{:.3f}x{:.3f}-{:.2f}kg".format(*size, mass)
    return ParcelAsset(asset_id=name, category="rectangular", split="test", mesh=mesh, mass=float(mass),
                       com=np.asarray(com, dtype=np.float64), rgba=tuple(rgba), extents=size)


@dataclass(frozen=True)
class PlacedBox:
    """A box placed by its bottom-face height (``z``, None: on the bin floor) and ``xy``, or by its
    ``center``; ``tilt`` turns it about its own x axis after the ``yaw``."""

    extents: tuple[float, float, float]
    mass: float
    xy: tuple[float, float] = (0.0, 0.0)
    yaw: float = 0.0
    z: float | None = None  # bottom face height; None rests it on the bin floor
    friction: float = 0.6
    rgba: tuple[float, float, float, float] = (0.75, 0.6, 0.4, 1.0)
    tilt: float = 0.0  # rad about the box's own x axis
    center: tuple[float, float, float] | None = None  # overrides xy and z

    def rotation(self) -> Rotation:
        # intrinsic ("ZX"): the tilt is about the box's own x axis once yawed (extrinsic "zx" tilted every
        # box about the world x, whatever its yaw; no scene combined the two before)
        return Rotation.from_euler("ZX", [self.yaw, self.tilt])

    def pose(self, floor_z: float) -> tuple[np.ndarray, np.ndarray]:
        """Centre position and xyzw orientation in the world."""
        if self.center is not None:
            pos = np.asarray(self.center, dtype=np.float64)
        else:
            z = floor_z if self.z is None else self.z
            pos = np.array([self.xy[0], self.xy[1], z + self.extents[2] / 2])
        return pos, self.rotation().as_quat()

    def resting_on_top(self, extents: tuple[float, float, float], mass: float, **kwargs) -> "PlacedBox":
        """A box of ``extents`` lying centred on this box's top face, tilted with it (needs ``center``)."""
        if self.center is None:
            raise ValueError("resting_on_top needs a support placed by its center")
        up = self.rotation().apply([0.0, 0.0, 1.0])
        centre = np.asarray(self.center) + up * (self.extents[2] + extents[2]) / 2
        return PlacedBox(extents, mass, yaw=self.yaw, tilt=self.tilt, center=tuple(centre.tolist()), **kwargs)


@dataclass(frozen=True)
class BoxScene:
    """A callable scene factory ``(sim, seed) -> Scene`` placing ``boxes`` in the bin, on or beside
    static ``fixtures`` (their mass is ignored)."""

    boxes: Sequence[PlacedBox]
    bin: BinSpec = field(default_factory=BinSpec)
    settle_steps: int = 240
    fixtures: Sequence[PlacedBox] = ()

    def __call__(self, sim: Simulator, seed: int) -> Scene:
        sim.reset()
        sim.add_bin(self.bin)
        fixtures = [self._add_fixture(sim, f) for f in self.fixtures]
        parcels: list[ParcelState] = []
        for i, b in enumerate(self.boxes):
            asset = box_asset(b.extents, b.mass, asset_id=f"placed-{i}", rgba=b.rgba)
            pos, orn = b.pose(self.bin.floor_z)
            body = sim.add_parcel(asset, pos.tolist(), orn.tolist(), b.friction)
            parcels.append(ParcelState(i, body, asset, pos, orn, b.friction))
        sim.settle([ps.body_id for ps in parcels], max_steps=self.settle_steps)
        for ps in parcels:
            ps.position, ps.orientation = sim.body_pose(ps.body_id)
        return Scene(parcels=parcels, bin=self.bin, seed=int(seed), layout="scattered",
                     object_set="rectangular", split="test", meta={"factory": "BoxScene", "fixtures": fixtures})

    def _add_fixture(self, sim: Simulator, box: PlacedBox) -> int:
        """A static box (a part of the cell, not a parcel)."""
        c = sim.client
        half = (np.asarray(box.extents, dtype=np.float64) / 2).tolist()
        pos, orn = box.pose(self.bin.floor_z)
        body = pb.createMultiBody(0.0, pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=c),
                                  pb.createVisualShape(pb.GEOM_BOX, halfExtents=half, rgbaColor=list(box.rgba),
                                                       physicsClientId=c),
                                  basePosition=pos.tolist(), baseOrientation=orn.tolist(), physicsClientId=c)
        pb.changeDynamics(body, -1, lateralFriction=box.friction, physicsClientId=c)
        return body
