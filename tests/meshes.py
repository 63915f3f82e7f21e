"""Known-answer test geometry shared by the suction tests: boxes, slabs and cylinders (world frame)."""

from __future__ import annotations

import numpy as np
import trimesh


def box(extents, centre) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(centre))


def horizontal_cylinder(radius: float, sections: int = 512) -> trimesh.Trimesh:
    """Axis along x through the origin, finely tessellated so facets do not bias the seal."""
    mesh = trimesh.creation.cylinder(radius=radius, height=0.3, sections=sections)
    return mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0)))


def tilted_plane(degrees: float) -> trimesh.Trimesh:
    """A 30 cm slab whose top, through the origin, is z = -x tan(theta)."""
    slab = box((0.3, 0.3, 0.05), (0, 0, -0.025))
    return slab.apply_transform(trimesh.transformations.rotation_matrix(np.radians(degrees), (0, 1, 0)))
