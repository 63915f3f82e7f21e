"""The one suction scorer of ParcelPick: labels, the env's seal check and the AP evaluator share it.

Everything is geometry on world-frame trimesh meshes (no pybullet): the Open3D ray scenes are
built once per scene in ``__init__`` and every score is one batched query over all candidates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np
import open3d as o3d
import trimesh

from parcelpick_env.suction.collision import collision_scores
from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.cup import CupSpec
from parcelpick_env.suction.cup_seal import ContactSeal, bellows_seal
from parcelpick_env.suction.geometry import O3D_INVALID_ID, build_scene, o3d_tensor, surface_centroid, validate_meshes
from parcelpick_env.suction.physical import PhysicalGrasp, hanging_ratios, hull_seats, lip_face, physical_tool
from parcelpick_env.suction.seal import SealScene, seal_scores
from parcelpick_env.suction.wrench import wrench_scores

if TYPE_CHECKING:
    from parcelpick_env.scene.scene import Scene

NORMAL_TOLERANCE = 1e-2  # |‖n‖ - 1| above this is a caller bug, not rounding
MAX_BATCH = 65536  # candidates per ray query: bounds the ray buffers to about 150 MB


@dataclass
class SuctionScores:
    """Per-candidate scores, each (N,) float32 in [0, 1]; ``total`` is their product, ``quality`` the product
    without visibility (what SuctionNet's AP scores)."""

    seal: np.ndarray
    wrench: np.ndarray
    collision: np.ndarray
    visibility: np.ndarray
    total: np.ndarray

    @property
    def quality(self) -> np.ndarray:
        return (self.seal * self.wrench * self.collision).astype(np.float32)

    def as_array(self) -> np.ndarray:
        """(N, 4) in the label order seal, wrench, collision, visibility."""
        return np.stack([self.seal, self.wrench, self.collision, self.visibility], axis=1)

    def __len__(self) -> int:
        return len(self.total)


class SuctionScorer:
    """Scores suction candidates ``(p, n)`` on a scene of world-frame parcel meshes.

    ``meshes[k]`` is parcel ``k`` (its object id), ``coms[k]`` its centre of mass and ``masses[k]`` its mass (kg;
    only ``physical`` needs them); ``obstacles`` (bin walls, floor) only block the tool.
    """

    def __init__(self, meshes: Sequence[trimesh.Trimesh], coms: np.ndarray,
                 obstacles: Sequence[trimesh.Trimesh] = (),
                 config: SuctionConfig = SuctionConfig(), masses: np.ndarray | None = None) -> None:
        if not isinstance(config, SuctionConfig):
            raise ValueError(f"config must be a SuctionConfig, got {type(config).__name__}")
        self.config = config
        self.meshes = validate_meshes(meshes, "meshes")
        self.obstacles = validate_meshes(obstacles, "obstacles")
        coms = np.asarray(coms, dtype=np.float64)
        if coms.shape != (len(self.meshes), 3) or not np.all(np.isfinite(coms)):
            raise ValueError(f"coms must be finite with shape ({len(self.meshes)}, 3), got {coms.shape}")
        self.coms = coms
        self.masses = None if masses is None else np.asarray(masses, dtype=np.float64)
        if self.masses is not None and (self.masses.shape != (len(self.meshes),) or not np.all(self.masses > 0)):
            raise ValueError(f"masses must be positive with shape ({len(self.meshes)},), got {self.masses!r}")
        # SuctionNet's wrench acts at the mean of a dense surface sample: the area-weighted surface centroid.
        self.surface_centroids = np.array([surface_centroid(m) for m in self.meshes]).reshape(-1, 3)
        self._seal_scene = SealScene(self.meshes, config)
        everything = self.meshes + self.obstacles
        self._collision_scene = build_scene(everything) if everything else None
        self._parcel_scene: o3d.t.geometry.RaycastingScene | None = None  # built on first use
        self._hull_scene: o3d.t.geometry.RaycastingScene | None = None  # parcels' hulls, then obstacles

    @classmethod
    def from_scene(cls, scene: "Scene", config: SuctionConfig = SuctionConfig(),
                   obstacles: Sequence[trimesh.Trimesh] | None = None) -> "SuctionScorer":
        """Scorer for a settled pile: its parcels, their centres of mass and masses, and the bin as obstacles
        (or ``obstacles``: SuctionNet's evaluator blocks the tool on the objects and the table only)."""
        return cls(scene.world_meshes(), scene.world_coms(), scene.bin.meshes() if obstacles is None else obstacles,
                   config, masses=scene.masses())

    def __getstate__(self) -> dict:
        """Pickle the geometry only (Open3D scenes cannot be pickled); they are rebuilt on load."""
        return {"meshes": self.meshes, "coms": self.coms, "obstacles": self.obstacles,
                "config": self.config, "masses": self.masses}

    def __setstate__(self, state: dict) -> None:
        type(self).__init__(self, state["meshes"], state["coms"], state["obstacles"], state["config"],
                            state.get("masses"))

    @property
    def num_objects(self) -> int:
        return len(self.meshes)

    # ------------------------------------------------------------------ scores
    def seal(self, points: np.ndarray, normals: np.ndarray, object_ids: np.ndarray) -> np.ndarray:
        """(N,) seal of the cup on each candidate's own object (0 for object ids < 0)."""
        points, normals = self._candidates(points, normals)
        object_ids = self._object_ids(object_ids, len(points))
        return self._seal(points, normals, object_ids)

    def contact_seal(self, tips: np.ndarray, axes: np.ndarray, object_ids: np.ndarray) -> ContactSeal:
        """Bellows seal of the cup where it actually is: lip centred at ``tips`` (N, 3), approaching
        along unit ``axes`` (N, 3) (tool into the object), on each ``object_ids`` parcel's true mesh.

        Unlike ``seal``, the gap between the lip and the true surface counts (a lip resting on a
        convex hull above a wrinkled top, or hovering, leaks). Needs ``seal_model="bellows"``.
        """
        if self.config.seal_model != "bellows":
            raise ValueError(f"contact_seal needs SuctionConfig(seal_model='bellows'), "
                             f"this scorer has seal_model={self.config.seal_model!r}")
        tips, axes = self._candidates(tips, axes, ("tips", "axes"))
        object_ids = self._object_ids(object_ids, len(tips))
        parts = [bellows_seal(self._seal_scene, tips[s], axes[s], object_ids[s], measure_gap=True)
                 for s in _batch_slices(len(tips))]
        return ContactSeal.concatenate(parts) if len(parts) != 1 else parts[0]

    def physical(self, points: np.ndarray, normals: np.ndarray, object_ids: np.ndarray,
                 cup: CupSpec = CupSpec()) -> PhysicalGrasp:
        """What the cell will find at each candidate, hanging still (``suction/physical.py``): the bellows seal
        where the cup rests on the parcel's hull, the ring ratios of the real mass at that seal's pull, and the
        physical tool's clearance against the hulls and obstacles. Needs ``seal_model="bellows"`` (the env's
        cup) and ``masses``; ids < 0 get seal 0, no collision clearance and infinite ratios."""
        if self.config.seal_model != "bellows" or self.masses is None:
            raise ValueError("physical scores need SuctionConfig(seal_model='bellows') (the env's cup) and the "
                             "parcels' masses")
        points, normals = self._candidates(points, normals)
        object_ids = self._object_ids(object_ids, len(points))
        if self._hull_scene is None:
            self._hull_scene = build_scene([m.convex_hull for m in self.meshes] + self.obstacles)
        face = lip_face(self.config)
        parts = []
        for s in _batch_slices(len(points)):
            p, n, ids = points[s], normals[s], object_ids[s]
            valid = ids >= 0
            tips, own = hull_seats(self._hull_scene, p, n, ids, face, self.config.num_threads)
            seal = np.zeros(len(p))
            ratios = np.full((len(p), 6), np.inf)
            if np.any(valid):
                contact = bellows_seal(self._seal_scene, tips[valid], -n[valid], ids[valid], measure_gap=True)
                seal[valid] = np.where(own[valid], contact.quality, 0.0)
                ratios[valid] = hanging_ratios(tips[valid], -n[valid], self.coms[ids[valid]], self.masses[ids[valid]],
                                               seal[valid], self.config, cup)
            collision = collision_scores(self._hull_scene, p, n, physical_tool(self.config))
            parts.append(PhysicalGrasp(seal=seal.astype(np.float32), ratios=ratios, seats=tips,
                                       collision=np.where(valid, collision, 0.0).astype(np.float32)))
        return PhysicalGrasp.concatenate(parts) if len(parts) != 1 else parts[0]

    def wrench(self, points: np.ndarray, normals: np.ndarray, object_ids: np.ndarray) -> np.ndarray:
        """(N,) wrench score against gravity on a unit mass (0 for ids < 0), by ``config.wrench_model``."""
        points, normals = self._candidates(points, normals)
        object_ids = self._object_ids(object_ids, len(points))
        return self._wrench(points, normals, object_ids)

    def collision(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(N,) 1 if the tool along ``n`` is free of parcels, bin and floor, else 0."""
        points, normals = self._candidates(points, normals)
        return self._collision(points, normals)

    def score(self, points: np.ndarray, normals: np.ndarray, object_ids: np.ndarray,
              visibility: np.ndarray | None = None) -> SuctionScores:
        """All four scores and their product; ``visibility`` is per object (M,), None means 1."""
        points, normals = self._candidates(points, normals)
        object_ids = self._object_ids(object_ids, len(points))
        vis = self.candidate_visibility(object_ids, visibility)
        seal = self._seal(points, normals, object_ids)
        wrench = self._wrench(points, normals, object_ids)
        collision = self._collision(points, normals)
        total = seal * wrench * collision * vis
        return SuctionScores(seal=seal, wrench=wrench, collision=collision, visibility=vis,
                             total=total.astype(np.float32))

    def candidate_visibility(self, object_ids: np.ndarray, visibility: np.ndarray | None) -> np.ndarray:
        """(N,) float32: each candidate's object's visibility (per object (M,), None means 1); 0 for ids < 0."""
        object_ids = self._object_ids(object_ids, len(np.asarray(object_ids).reshape(-1)))
        per_object = self._visibility(visibility)
        out = np.zeros(len(object_ids), dtype=np.float32)
        valid = object_ids >= 0
        out[valid] = per_object[object_ids[valid]]
        return out

    def nearest_object(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Object id of the closest parcel surface to each point, and the distance to it.

        With no parcels every id is -1 and every distance inf.
        """
        points = self._points(points)
        if self.num_objects == 0 or len(points) == 0:
            return np.full(len(points), -1, dtype=np.int64), np.full(len(points), np.inf)
        if self._parcel_scene is None:
            self._parcel_scene = build_scene(self.meshes)
        closest = self._parcel_scene.compute_closest_points(
            o3d_tensor(points.astype(np.float32)), nthreads=self.config.num_threads)
        ids = closest["geometry_ids"].numpy().astype(np.int64)
        ids[ids == O3D_INVALID_ID] = -1
        distances = np.linalg.norm(closest["points"].numpy().astype(np.float64) - points, axis=1)
        return ids, distances

    # ------------------------------------------------------------------ helpers
    def _seal(self, points: np.ndarray, normals: np.ndarray, object_ids: np.ndarray) -> np.ndarray:
        if self.config.seal_model == "bellows":  # the cup pressed along -n to first touch (gap 0)
            return _in_batches(lambda p, n, i: bellows_seal(self._seal_scene, p, -n, i, measure_gap=False).quality,
                               points, normals, object_ids)
        return _in_batches(lambda *a: seal_scores(self._seal_scene, *a), points, normals, object_ids)

    def _collision(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        return _in_batches(lambda p, n: collision_scores(self._collision_scene, p, n, self.config),
                           points, normals)

    def _wrench(self, points: np.ndarray, normals: np.ndarray, object_ids: np.ndarray) -> np.ndarray:
        out = np.zeros(len(points), dtype=np.float32)
        valid = object_ids >= 0
        if np.any(valid):
            centres = self.coms if self.config.wrench_model == "paper" else self.surface_centroids
            out[valid] = wrench_scores(points[valid], normals[valid], centres[object_ids[valid]], self.config)
        return out

    @staticmethod
    def _points(points: np.ndarray, name: str = "points") -> np.ndarray:
        points = np.asarray(points)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"{name} must have shape (N, 3), got {points.shape}")
        if not np.issubdtype(points.dtype, np.number):
            raise ValueError(f"{name} must be numeric, got dtype {points.dtype}")
        points = points.astype(np.float64)
        if not np.all(np.isfinite(points)):
            raise ValueError(f"{name} must be finite (found NaN or inf)")
        return points

    def _candidates(self, points: np.ndarray, normals: np.ndarray,
                    names: tuple[str, str] = ("points", "normals")) -> tuple[np.ndarray, np.ndarray]:
        points = self._points(points, names[0])
        normals = self._points(normals, names[1])
        if len(normals) != len(points):
            raise ValueError(f"{names[0]} and {names[1]} differ in length: {len(points)} vs {len(normals)}")
        norms = np.linalg.norm(normals, axis=1, keepdims=True)
        if np.any(np.abs(norms - 1.0) > NORMAL_TOLERANCE):
            raise ValueError(f"{names[1]} must be unit vectors (found a norm off by more than 1e-2)")
        return points, normals / norms

    def _object_ids(self, object_ids: np.ndarray, count: int) -> np.ndarray:
        object_ids = np.asarray(object_ids)
        if object_ids.shape != (count,):
            raise ValueError(f"object_ids must have shape ({count},), got {object_ids.shape}")
        if count and not np.issubdtype(object_ids.dtype, np.integer):
            raise ValueError(f"object_ids must be integers, got dtype {object_ids.dtype}")
        object_ids = object_ids.astype(np.int64)
        if count and object_ids.max() >= self.num_objects:
            raise ValueError(f"object id {object_ids.max()} out of range for {self.num_objects} objects")
        return object_ids

    def _visibility(self, visibility: np.ndarray | None) -> np.ndarray:
        if visibility is None:
            return np.ones(self.num_objects, dtype=np.float32)
        visibility = np.asarray(visibility, dtype=np.float64)
        if visibility.shape != (self.num_objects,):
            raise ValueError(f"visibility must be per object, shape ({self.num_objects},), "
                             f"got {visibility.shape}")
        if not np.all(np.isfinite(visibility)) or np.any(visibility < 0) or np.any(visibility > 1):
            raise ValueError("visibility ratios must be finite and in [0, 1]")
        return visibility.astype(np.float32)


def _batch_slices(count: int) -> list[slice]:
    """Slices of at most ``MAX_BATCH`` candidates covering ``count`` (one, possibly empty, at least)."""
    return [slice(start, start + MAX_BATCH) for start in range(0, max(count, 1), MAX_BATCH)]


def _in_batches(fn, *arrays: np.ndarray) -> np.ndarray:
    """``fn`` over at most ``MAX_BATCH`` candidates at a time, concatenated (bounded memory)."""
    count = len(arrays[0])
    if count <= MAX_BATCH:
        return fn(*arrays)
    return np.concatenate([fn(*(a[s] for a in arrays)) for s in _batch_slices(count)])
