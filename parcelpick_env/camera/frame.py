"""One capture of the overhead camera."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

BACKGROUND = -1  # segmentation label of the bin, floor and anything that is not a parcel


@dataclass
class CameraFrame:
    """Images and the derived world-frame point cloud.

    ``intrinsics`` is the 3x3 pinhole matrix K; ``extrinsics`` is the 4x4 camera-to-world transform
    in the OpenCV convention (x right, y down, z forward). ``depth`` is metric z-depth with 0 where
    the sensor returned nothing. ``segmentation`` holds scene object ids, ``BACKGROUND`` elsewhere.
    ``points``/``normals``/``point_object_ids``/``point_pixels`` describe every valid depth pixel;
    normals are Open3D estimates oriented towards the camera (outward from the surface), or empty (0, 3)
    when captured with ``normals=False`` (``Camera.normals_at`` then gives them where needed).
    """

    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32, metres
    segmentation: np.ndarray  # (H, W) int32
    intrinsics: np.ndarray  # (3, 3) float64
    extrinsics: np.ndarray  # (4, 4) float64, camera -> world
    points: np.ndarray  # (P, 3) float32, world frame
    normals: np.ndarray  # (P, 3) float32, unit, outward
    point_object_ids: np.ndarray  # (P,) int32
    point_pixels: np.ndarray  # (P, 2) int32, (row, col)
    # the float64 cloud ``points`` was rounded from, kept by ``Camera.capture`` so that ``Camera.normals_at``
    # estimates on exactly what ``capture`` would have without back-projecting the image again
    points64: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])
