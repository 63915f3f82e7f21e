"""Collision score: does any scene geometry enter the suction tool's cylinder(s) above the contact?

The tool is a solid cylinder of radius ``R`` spanning ``[near, far]`` along ``n`` (plus an optional
wider body cylinder). It is probed with ray *segments* against every parcel, bin and floor mesh,
in one batched any-hit query (Open3D ``test_occlusions``):

* axial segments from ``p + near n`` to ``p + far n``, on the axis and on rings at ``R/2`` and
  ``R``, at most 5.5 mm apart (19 at R = 10 mm; more on a wider body): any surface crossing the
  cylinder transversally (a parcel lying above, the top or bottom face of anything ending inside
  the tool's span) cuts them;
* 12 diameters across the cylinder, in 3 directions 60 degrees apart, at 4 levels from ``near`` to
  ``far``: a surface running along the axis over the whole span (a bin wall or a tall parcel side
  clipping the tool) has no face crossing the axial segments, but cuts these.

Approximation: a closed object intruding into the cylinder either crosses the axial segments with
its end faces or spans the tool's length and meets the diameters; what can be missed is an
intrusion shallower than about 0.4 mm at the ring's 5.5 mm spacing, or a surface parallel to the
axis that starts and ends between two diameter levels without an end face inside the cylinder (an
open sheet). The candidate's own surface below ``p + near n`` is never tested, as in SuctionNet.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.geometry import frame_rays, ring_pattern, tangent_frames

AXIAL_RADII = (0.0, 0.5, 1.0)  # fractions of the cylinder radius
AXIAL_SPACING = 0.0055  # m between axial segments on a ring: 6 and 12 at the default R = 10 mm
DIAMETER_DIRECTIONS = 3
DIAMETER_LEVELS = 4


def cylinder_segments(radius: float, near: float, far: float) -> np.ndarray:
    """(K, 6) frame-ray coefficients of the segments probing one cylinder (see module docstring).

    Each direction is the whole segment, so ``t`` in [0, 1] spans exactly the segment.
    """
    radii = [f * radius for f in AXIAL_RADII]
    counts = [max(1, int(np.ceil(2 * np.pi * ring / AXIAL_SPACING))) for ring in radii]
    axial = ring_pattern(radii, counts)
    axial_rows = np.zeros((len(axial), 6))
    axial_rows[:, :2] = axial
    axial_rows[:, 2] = near
    axial_rows[:, 5] = far - near

    levels = np.linspace(near, far, DIAMETER_LEVELS)
    angles = np.pi * np.arange(DIAMETER_DIRECTIONS) / DIAMETER_DIRECTIONS
    ends = radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    cross_rows = np.zeros((len(ends) * len(levels), 6))
    cross_rows[:, :2] = np.repeat(-ends, len(levels), axis=0)
    cross_rows[:, 2] = np.tile(levels, len(ends))
    cross_rows[:, 3:5] = np.repeat(2.0 * ends, len(levels), axis=0)
    return np.concatenate([axial_rows, cross_rows], axis=0)


def tool_segments(config: SuctionConfig) -> np.ndarray:
    """Segments of the tool cylinder, plus the body cylinder when ``body_radius > 0``."""
    segments = cylinder_segments(config.tool_radius, config.tool_near, config.tool_far)
    if config.body_radius > 0:
        body = cylinder_segments(config.body_radius, config.body_near, config.body_far)
        segments = np.concatenate([segments, body], axis=0)
    return segments


def collision_scores(scene: o3d.t.geometry.RaycastingScene | None, points: np.ndarray,
                     normals: np.ndarray, config: SuctionConfig) -> np.ndarray:
    """(N,) 1 where the tool is free, 0 where any segment touches the scene."""
    if scene is None or len(points) == 0:
        return np.ones(len(points), dtype=np.float32)
    rays = frame_rays(points, normals, *tangent_frames(normals), tool_segments(config))
    hit = scene.test_occlusions(rays, tnear=0.0, tfar=1.0, nthreads=config.num_threads).numpy()
    return (~hit.reshape(len(points), -1).any(axis=1)).astype(np.float32)
