"""Seal score on the object's true mesh: the paper's compliant spring rim, or SuctionNet's evaluator seal.

docs/labels.md, 'Seal'. The 72 rim vertices are projected along ``-n`` by ray casting. A
candidate may only seal on ITS object, so every parcel is copied into its own cell of one ray
scene (cells far enough apart that no ray reaches a neighbour within the accepted depth); the
rays of a candidate on object ``k`` are shifted into cell ``k``. All ``N * (72 + interior)``
rays then go through a single ``cast_rays`` call and only hits on geometry ``k`` count.

``seal_model="suctionnet"`` is SuctionNet-1Billion's evaluator (``get_smoothness_score``): each of the 72 rim
vertices takes the HIGHEST surface point of its angular bin over the annulus ``r +- 1 mm``, which SuctionNet reads
off a dense (0.2 mm) surface sample. A ray cast from above finds the highest surface point of its column exactly,
so each bin here is the maximum over a 3 x 3 grid of columns (3 radii across the annulus, 3 headings across the
bin, ``SUCTIONNET_BIN_RAYS``); a bin none of them hits is empty, and an empty bin fails the seal, as there.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import trimesh

from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.geometry import build_scene, frame_rays, ring_pattern, tangent_frames

# Rays inside the cup disk that look for an obstruction: the centre and rings at r/3 and 2r/3.
OBSTRUCTION_RADII = (0.0, 1.0 / 3.0, 2.0 / 3.0)
OBSTRUCTION_COUNTS = (1, 6, 12)
# SuctionNet tests every dense point inside the disk; the suctionnet model probes it more densely (81 rays).
SUCTIONNET_OBSTRUCTION_RADII = (0.0, 0.25, 0.5, 0.75, 0.95)
SUCTIONNET_OBSTRUCTION_COUNTS = (1, 8, 16, 24, 32)
# SuctionNet's rim: the points 9-11 mm from the axis at r = 10 mm, i.e. r +- 1 mm (a fixed band, as there).
SUCTIONNET_RIM_BAND = 0.001
SUCTIONNET_BAND_RADII = (-1.0, 0.0, 1.0)  # in units of the band: inner edge, rim, outer edge
SUCTIONNET_BIN_HEADINGS = (-1.0 / 3.0, 0.0, 1.0 / 3.0)  # in units of the bin's angular width, about its centre
SUCTIONNET_BIN_RAYS = len(SUCTIONNET_BAND_RADII) * len(SUCTIONNET_BIN_HEADINGS)
# SuctionNet's fit term: exp(-FIT_GAIN * variance of rim heights (m^2)).
FIT_GAIN = 1e5


class SealScene:
    """Every parcel laid out in its own cell of one Open3D ray scene (see module docstring)."""

    def __init__(self, meshes: Sequence[trimesh.Trimesh], config: SuctionConfig) -> None:
        self.config = config
        self.num_objects = len(meshes)
        self.offsets = np.zeros((self.num_objects, 3))
        # Closed, consistently wound, outward meshes let the seal reject hits on a face's back side
        # (a flipped normal, or a ray starting inside the solid).
        self.oriented = np.array([bool(m.is_watertight and m.is_winding_consistent and m.volume > 0)
                                  for m in meshes], dtype=bool)
        if self.num_objects == 0:
            self.scene = None
            return
        lo = np.array([m.bounds[0] for m in meshes])
        hi = np.array([m.bounds[1] for m in meshes])
        reach = 2 * config.ray_offset + config.max_ray_depth + config.cup_radius
        cell = float(np.max(hi - lo)) + 2 * reach + 0.1
        side = int(np.ceil(np.sqrt(self.num_objects)))
        index = np.arange(self.num_objects)
        grid = np.stack([index % side, index // side], axis=1) - (side - 1) / 2.0
        centres = np.zeros((self.num_objects, 3))
        centres[:, :2] = grid * cell
        self.offsets = centres - (lo + hi) / 2.0
        self.scene = build_scene(meshes, self.offsets)

    @classmethod
    def of_surface(cls, surface: trimesh.Trimesh, config: SuctionConfig) -> "SealScene":
        """One open surface (an observed depth mesh, not a closed parcel) as object 0, left in place: with one
        object there is no neighbour to keep the rays from, and an open surface has no inside to test for."""
        scene = cls([], config)
        scene.num_objects = 1
        scene.offsets = np.zeros((1, 3))
        scene.oriented = np.zeros(1, dtype=bool)
        scene.scene = build_scene([surface])
        return scene


def rim_rays_per_vertex(config: SuctionConfig) -> int:
    """Rays cast for each rim vertex: 1 (exactly on the rim), or the suctionnet bin's ``SUCTIONNET_BIN_RAYS``."""
    return SUCTIONNET_BIN_RAYS if config.seal_model == "suctionnet" else 1


def seal_ray_pattern(config: SuctionConfig) -> np.ndarray:
    """Frame-ray coefficients: rim rays first (``rim_vertices * rim_rays_per_vertex``, vertex-major), then the
    obstruction rays inside the disk.

    Every ray starts ``ray_offset`` above the cup plane and points along ``-n``.
    """
    r, count = config.cup_radius, config.rim_vertices
    if config.seal_model == "suctionnet":
        width = 2.0 * np.pi / count
        heading = (np.arange(count)[:, None, None] + np.asarray(SUCTIONNET_BIN_HEADINGS)[None, None, :]) * width
        radius = r + SUCTIONNET_RIM_BAND * np.asarray(SUCTIONNET_BAND_RADII)[None, :, None]
        heading, radius = np.broadcast_arrays(heading, radius)  # (vertices, radii, headings)
        rim = np.stack([radius * np.cos(heading), radius * np.sin(heading)], axis=-1).reshape(-1, 2)
        inner = ring_pattern([f * r for f in SUCTIONNET_OBSTRUCTION_RADII], SUCTIONNET_OBSTRUCTION_COUNTS)
    else:
        rim = ring_pattern([r], [count])
        inner = ring_pattern([f * r for f in OBSTRUCTION_RADII], OBSTRUCTION_COUNTS)
    planar = np.concatenate([rim, inner], axis=0)
    coefficients = np.zeros((len(planar), 6))
    coefficients[:, :2] = planar
    coefficients[:, 2] = config.ray_offset
    coefficients[:, 5] = -1.0
    return coefficients


def seal_scores(seal_scene: SealScene, points: np.ndarray, normals: np.ndarray,
                object_ids: np.ndarray) -> np.ndarray:
    """(N,) seal in [0, 1]; 0 for object ids < 0, rim misses and obstructions."""
    config = seal_scene.config
    out = np.zeros(len(points), dtype=np.float32)
    valid = object_ids >= 0
    if seal_scene.scene is None or not np.any(valid):
        return out
    p, n, ids = points[valid], normals[valid], object_ids[valid]
    rays = frame_rays(p + seal_scene.offsets[ids], n, *tangent_frames(n), seal_ray_pattern(config))
    hits = seal_scene.scene.cast_rays(rays, nthreads=config.num_threads)
    count, per_vertex = len(p), rim_rays_per_vertex(config)
    num_rim = config.rim_vertices * per_vertex
    t_hit = hits["t_hit"].numpy().reshape(count, -1)
    on_object = hits["geometry_ids"].numpy().reshape(count, -1) == ids.astype(np.uint32)[:, None]

    # Height of the surface above the cup plane, along n, under every ray (float32 is ample:
    # t ~ 0.05 m has a resolution of 4e-9 m).
    height = np.float32(config.ray_offset) - t_hit
    rim_height, inner_height = height[:, :num_rim], height[:, num_rim:]
    rim_ok = on_object[:, :num_rim] & (rim_height >= -config.max_ray_depth)
    if per_vertex > 1:  # suctionnet: each vertex is the highest surface point of its bin; an empty bin fails
        binned = rim_ok.reshape(count, config.rim_vertices, per_vertex)
        rim_height = np.where(binned, rim_height.reshape(binned.shape), -np.inf).max(axis=2)
        rim_ok = binned.any(axis=2)

    # Inside the disk: surface standing too high above p obstructs the cup, and so does a hit
    # on a face's back side (p lies under the solid, e.g. a flipped normal) on an oriented mesh.
    inner_normals = hits["primitive_normals"].numpy().reshape(count, -1, 3)[:, num_rim:]
    back = np.einsum("nkc,nc->nk", inner_normals, n.astype(np.float32)) <= 0
    back &= seal_scene.oriented[ids][:, None]
    obstructed = np.any(on_object[:, num_rim:]
                        & ((inner_height > config.obstruction_height) | back), axis=1)
    ok = np.all(rim_ok, axis=1) & ~obstructed

    rim_height = rim_height[ok].astype(np.float64)
    chord = 2.0 * config.cup_radius * np.sin(np.pi / config.rim_vertices)  # l_i, identical for all i
    # Projection moves vertices only along n, orthogonal to the chords, so l~_i follows exactly:
    # l~_i / l_i = sqrt(1 + (dh_i / l_i)^2), largest where |dh_i| is.
    dh = np.maximum(np.abs(rim_height[:, 1:] - rim_height[:, :-1]).max(axis=1, initial=0.0),
                    np.abs(rim_height[:, 0] - rim_height[:, -1]) if len(rim_height) else 0.0)
    stretch = np.sqrt(1.0 + (dh / chord) ** 2)  # max_i l~_i / l_i
    if config.seal_model == "spring":
        seal = 1.0 - np.minimum(1.0, stretch - 1.0)
    else:  # suctionnet: fit * deform, deform = min_i l_i / l~_i
        seal = np.exp(-FIT_GAIN * rim_height.var(axis=1)) / stretch
    scores = np.zeros(count, dtype=np.float32)
    scores[ok] = np.clip(seal, 0.0, 1.0)
    out[valid] = scores
    return out
