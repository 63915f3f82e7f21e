"""Which candidate picks lie on a surface that something the camera sees rises above: a parcel under another.

Lifting a parcel that others rest or lean on drags them with it, about the cup's axis, and the 40 mm lip's torsion
capacity (0.1-0.3 N m) rarely holds that: on the report's stacked piles Diffusion-Suction held 96% of its picks of
free parcels and 62% of its picks of covered ones, and took most of those while a free parcel was left (README,
'Where the stacked cells' attempts go'). A cell that picks the top layer first avoids that, and it needs no ground
truth for it: a covered parcel's visible face is bordered by a surface that rises above it.

The test, per smooth surface segment of the observed cloud (``policies.surface_segments``): depth samples inside the
bin that lie within ``reach`` (horizontally) of one of its points and more than ``rise`` above that point's tangent
plane. A convex parcel's own surface lies below every tangent plane, so its faces never border themselves; the bin's
walls lie outside the workspace the test keeps. A neighbour standing taller beside the parcel counts too, which is
what a top-layer-first cell wants.
"""

from __future__ import annotations

from dataclasses import dataclass
from numbers import Real
from typing import Any, Mapping

import numpy as np
from scipy.spatial import cKDTree

from parcelpick_env.config_checks import (require, require_finite_numbers, require_positive_ints,
                                          require_positive_numbers)
from policies.heatmap import pixels_to_world
from policies.observation import camera, depth_image, in_box, point_cloud, workspace
from policies.surface_segments import segment_surfaces


@dataclass(frozen=True)
class ExposureConfig:
    """``reach``: horizontal distance (m) from a segment's points within which a rise counts; ``rise``: height (m)
    above the point's tangent plane that counts as rising above it; ``min_samples``: distinct depth samples above a
    segment before it counts as bordered (depth noise and single stray pixels do not); ``stride``: depth pixels
    between samples; ``wall_margin``: the workspace shrunk by this much (m) in x and y, so the walls stay out;
    ``match``: candidates farther than this (m) from every observed point are left unjudged (exposed)."""

    reach: float = 0.02
    rise: float = 0.01
    min_samples: int = 6
    stride: int = 2
    wall_margin: float = 0.005
    match: float = 0.01

    def __post_init__(self) -> None:
        require_positive_numbers(self, ("reach", "rise", "match"))
        require_finite_numbers(self, ("wall_margin",))
        require(self.wall_margin >= 0, "ExposureConfig", f"wall_margin must be >= 0, got {self.wall_margin!r}")
        require_positive_ints(self, ("min_samples", "stride"))


def check_covered_factor(owner: str, value: object) -> None:
    """``value`` is the score factor of a covered pick, a number in [0, 1] (1: not judged); else one ValueError
    naming ``owner`` and the field."""
    ok = isinstance(value, Real) and not isinstance(value, bool) and 0.0 <= float(value) <= 1.0
    require(ok, owner, f"covered_factor must be a number in [0, 1], got {value!r}")


def bordered_segments(points: np.ndarray, normals: np.ndarray, labels: np.ndarray, samples: np.ndarray,
                      config: ExposureConfig = ExposureConfig()) -> np.ndarray:
    """(labels.max() + 1,) bool: segments with at least ``min_samples`` of ``samples`` (depth points, world) within
    ``reach`` of one of their points horizontally and more than ``rise`` above its tangent plane. ``normals`` face
    the camera (up)."""
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    samples = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
    count = int(labels.max()) + 1 if len(labels) else 0
    if count == 0 or len(samples) == 0:
        return np.zeros(count, dtype=bool)
    pairs = cKDTree(points[:, :2]).sparse_distance_matrix(cKDTree(samples[:, :2]), config.reach,
                                                           output_type="ndarray")
    i, j = pairs["i"], pairs["j"]
    above = np.einsum("ij,ij->i", samples[j] - points[i], normals[i]) > config.rise
    # distinct samples per segment: a sample above many of a segment's points is still one sample
    keys = np.unique(labels[i[above]].astype(np.int64) * len(samples) + j[above])
    return np.bincount(keys // len(samples), minlength=count) >= config.min_samples


def exposed_picks(obs: Mapping[str, Any], info: Mapping[str, Any] | None, picks: np.ndarray,
                  config: ExposureConfig = ExposureConfig()) -> np.ndarray:
    """(K,) bool: each pick's surface (the segment of its nearest observed point) is not bordered from above."""
    picks = np.asarray(picks, dtype=np.float64).reshape(-1, 3)
    points, normals = point_cloud(obs, "the exposure check", drop_invalid=True)
    if len(picks) == 0 or len(points) == 0:
        return np.ones(len(picks), dtype=bool)
    K, T = camera(info, "the exposure check")
    depth = depth_image(obs, "the exposure check")
    rows, cols = np.mgrid[0:depth.shape[0]:config.stride, 0:depth.shape[1]:config.stride]
    rows, cols = rows.ravel(), cols.ravel()
    valid = depth[rows, cols] > 0
    samples = pixels_to_world(rows[valid], cols[valid], depth, K, T)
    box = workspace(info, "the exposure check")
    if box is not None:
        shrink = np.array([config.wall_margin, config.wall_margin, 0.0])
        samples = samples[in_box(samples, box[0] + shrink, box[1] - shrink)]
    labels = segment_surfaces(points, normals)
    bordered = bordered_segments(points, normals, labels, samples, config)
    distance, nearest = cKDTree(points).query(picks)
    return ~(bordered[labels[nearest]] & (distance <= config.match))
