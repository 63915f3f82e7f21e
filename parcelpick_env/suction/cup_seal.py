"""Seal of a bellows cup, decided by the cup's compliance on the object's true mesh (docs/cup_seal.md).

The cup is a lip circle of radius ``r = SuctionConfig.cup_radius`` centred on the tool tip ``t``, in
the plane orthogonal to the approach axis ``a`` (pointing from the tool into the object). Rays are
cast along ``a`` through the rim and the disk inside it (the spring model's ray pattern, in the same
per-object ray scene, one ``cast_rays`` call); ``d`` is each hit's depth below the lip plane along
``a`` (negative: the surface stands above the lip). A plane ``d = c0 + gx x + gy y`` is fitted to the
rim hits by least squares, and the cup's compliance (``BellowsCup``) takes up what it can:

- **tilt** ``atan |(gx, gy)|``: the bellows bends its lip onto the fitted plane, up to ``max_bend``;
- **residual**, half the band of the rim's residuals about that plane: the lip and lowest fold give
  ``lip_compliance`` either way (this is what a 90 degree edge or a tight curvature exceeds);
- **stroke**: the lip pressed in at first touch (``-gap``) plus whatever rises inside the cup above
  the fitted lip plane must fit in the bellows' axial ``stroke``;
- **gap** ``min_i d_i``: how far the lip still hovers above the surface at its first touch; vacuum
  flow pulls a lip shut across at most ``leak_gap``.

Each margin ``u = value / limit`` scores ``1 - u**2`` (1 when the cup is not strained at all, falling
smoothly to 0 at the limit, no cliff); the seal quality is their product. When it is 0 the first
limit reached, in the order miss, obstruction (a rim or disk ray meets the inside of a closed mesh),
edge, tilt, obstruction (stroke), gap, is the reason.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np

from parcelpick_env.suction.geometry import frame_rays, tangent_frames
from parcelpick_env.suction.seal import SealScene, seal_ray_pattern

SEAL_REASONS: tuple[str, ...] = ("sealed", "miss", "edge", "tilt", "obstruction", "gap")
SEALED, MISS, EDGE, TILT, OBSTRUCTION, GAP = range(len(SEAL_REASONS))


@dataclass
class ContactSeal:
    """Per-candidate bellows seal, each field (N,).

    ``quality`` float32 in [0, 1]; ``reason`` int8 index into ``SEAL_REASONS`` (``SEALED`` exactly
    where quality > 0). Measures in metres / radians, NaN where no rim fit exists (a miss):
    ``gap`` signed lip-to-surface distance at first touch along ``a`` (+: the lip hovers, -: pressed
    in; 0 for surface candidates, whose cup is placed at first touch), ``tilt`` of the fitted rim
    plane to the cup plane, ``residual`` half-band of the rim about that plane, ``rise`` of the disk
    above the fitted plane (>= 0).
    """

    quality: np.ndarray
    reason: np.ndarray
    gap: np.ndarray
    tilt: np.ndarray
    residual: np.ndarray
    rise: np.ndarray

    REASONS: ClassVar[tuple[str, ...]] = SEAL_REASONS

    @classmethod
    def empty(cls, count: int) -> "ContactSeal":
        """``count`` misses: quality 0, reason ``MISS``, NaN measures."""
        nan = np.full(count, np.nan)
        return cls(quality=np.zeros(count, dtype=np.float32), reason=np.full(count, MISS, dtype=np.int8),
                   gap=nan.copy(), tilt=nan.copy(), residual=nan.copy(), rise=nan.copy())

    @classmethod
    def concatenate(cls, parts: Sequence["ContactSeal"]) -> "ContactSeal":
        return cls(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)})

    def reason_names(self) -> np.ndarray:
        """(N,) reason strings, e.g. ``'sealed'``, ``'edge'``."""
        return np.asarray(SEAL_REASONS)[self.reason]

    def __len__(self) -> int:
        return len(self.quality)


def taper(u: np.ndarray) -> np.ndarray:
    """Quality left at margin ``u`` = strain / limit: 1 at 0, 0 at and beyond 1, smooth in between."""
    return np.clip(1.0 - np.square(u), 0.0, 1.0)


def rim_plane_fit(planar: np.ndarray) -> np.ndarray:
    """(3, K) least-squares operator: ``depth (N, K) @ op.T`` is ``(c0, gx, gy)`` of the rim plane."""
    design = np.concatenate([np.ones((len(planar), 1)), planar], axis=1)
    return np.linalg.pinv(design)


def bellows_seal(seal_scene: SealScene, tips: np.ndarray, axes: np.ndarray, object_ids: np.ndarray,
                 measure_gap: bool) -> ContactSeal:
    """Bellows seal of a cup with its lip centred at ``tips`` (N, 3), approaching along unit ``axes``.

    Only hits on each candidate's own object count (object ids < 0 miss). ``measure_gap=False``
    places the cup at first touch (surface candidates: the gap is 0 and takes none of the stroke).
    """
    config = seal_scene.config
    cup = config.bellows
    out = ContactSeal.empty(len(tips))
    valid = object_ids >= 0
    if seal_scene.scene is None or not np.any(valid):
        return out
    t, n, ids = tips[valid], -axes[valid], object_ids[valid]
    pattern = seal_ray_pattern(config)  # rim rays first, then the disk; start ray_offset behind the lip
    hits = seal_scene.scene.cast_rays(frame_rays(t + seal_scene.offsets[ids], n, *tangent_frames(n), pattern),
                                      nthreads=config.num_threads)
    count, num_rim = len(t), config.rim_vertices
    depth = hits["t_hit"].numpy().reshape(count, -1).astype(np.float64) - config.ray_offset
    on_object = hits["geometry_ids"].numpy().reshape(count, -1) == ids.astype(np.uint32)[:, None]
    reached = on_object & (depth <= config.max_ray_depth)
    rim_ok = np.all(reached[:, :num_rim], axis=1)
    # A hit on a face's back side of a closed, outward mesh: the lip or the disk is inside the solid.
    hit_normals = hits["primitive_normals"].numpy().reshape(count, -1, 3)
    back = np.einsum("nkc,nc->nk", hit_normals, n.astype(np.float32)) <= 0
    inside = np.any(reached & back & seal_scene.oriented[ids][:, None], axis=1)

    # Rim plane by least squares (misses carry depth inf; their rows are discarded below).
    rim = np.where(reached[:, :num_rim], depth[:, :num_rim], 0.0)
    coef = rim @ rim_plane_fit(pattern[:num_rim, :2]).T  # (N, 3): c0, gx, gy
    residuals = rim - (coef[:, :1] + coef[:, 1:] @ pattern[:num_rim, :2].T)
    residual = 0.5 * (residuals.max(axis=1) - residuals.min(axis=1))
    tilt = np.arctan(np.hypot(coef[:, 1], coef[:, 2]))
    # Disk: the surface's height above the fitted lip plane, where a disk ray meets the object.
    plane_inner = coef[:, :1] + coef[:, 1:] @ pattern[num_rim:, :2].T
    rise_k = np.where(reached[:, num_rim:], plane_inner - depth[:, num_rim:], 0.0)
    rise = np.maximum(rise_k.max(axis=1, initial=0.0), 0.0)
    gap = rim.min(axis=1) if measure_gap else np.zeros(count)

    u_edge = residual / cup.lip_compliance
    u_tilt = tilt / cup.max_bend_rad
    u_stroke = (np.maximum(-gap, 0.0) + rise) / cup.stroke
    u_gap = np.maximum(gap, 0.0) / cup.leak_gap
    fit = rim_ok & ~inside
    quality = np.where(fit, taper(u_edge) * taper(u_tilt) * taper(u_stroke) * taper(u_gap), 0.0)
    reason = np.select([~rim_ok, inside, u_edge >= 1, u_tilt >= 1, u_stroke >= 1, u_gap >= 1],
                       [MISS, OBSTRUCTION, EDGE, TILT, OBSTRUCTION, GAP], default=SEALED)

    out.quality[valid] = quality.astype(np.float32)
    out.reason[valid] = reason.astype(np.int8)
    for name, value in (("gap", gap), ("tilt", tilt), ("residual", residual), ("rise", rise)):
        getattr(out, name)[valid] = np.where(rim_ok, value, np.nan)
    return out
